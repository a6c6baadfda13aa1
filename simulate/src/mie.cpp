#include "raymatch/simulate/mie.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace raymatch::simulate {

int MieTerms(double x) { return static_cast<int>(std::lround(x + 4.05 * std::cbrt(x) + 2)); }

namespace {

/// D_n(z) = psi_n'(z) / psi_n(z) for one n, from J_{n-1/2}(z) / J_{n+1/2}(z) by Lentz's
/// continued fraction (modified Lentz evaluation): D_n = -n / z + [a_1; a_2, ...] with
/// a_k = (-1)^(k+1) (2n + 2k - 1) / z.
Complex LogDerivativeStart(int n, Complex z) {
  constexpr double kTiny = 1e-300, kEps = 1e-15;
  auto a = [&](int k) { return (k % 2 ? 1.0 : -1.0) * (2.0 * n + 2.0 * k - 1.0) / z; };
  Complex f = a(1);
  if (std::abs(f) < kTiny) f = kTiny;
  Complex c = f, d = 0;
  for (int k = 2; k < 100000 + 10 * int(std::abs(z)); ++k) {
    const Complex b = a(k);
    d = b + d;
    if (std::abs(d) < kTiny) d = kTiny;
    c = b + 1.0 / c;
    if (std::abs(c) < kTiny) c = kTiny;
    d = 1.0 / d;
    const Complex delta = c * d;
    f *= delta;
    if (std::abs(delta - 1.0) < kEps) break;
  }
  return -double(n) / z + f;
}

void CheckIndex(Complex m) {
  if (!(m.real() > 0) || m.imag() < 0)
    throw std::invalid_argument("Mie: relative index needs Re m > 0 and Im m >= 0");
}

void CheckSize(double x) {
  if (!(x > 0) || !std::isfinite(x))
    throw std::invalid_argument("Mie: size parameter must be positive, got " + std::to_string(x));
}

/// D_n(z) for n = 0..n_terms: downward recurrence D_{n-1} = n / z - 1 / (D_n + n / z) from a
/// continued-fraction start, stable for any |z|.
std::vector<Complex> LogDerivatives(Complex z, int n_terms) {
  std::vector<Complex> dn(n_terms + 1);
  dn[n_terms] = LogDerivativeStart(n_terms, z);
  for (int n = n_terms; n >= 1; --n) dn[n - 1] = double(n) / z - 1.0 / (dn[n] + double(n) / z);
  return dn;
}

/// a_n, b_n from the logarithmic derivatives H^a_n, H^b_n (n = 1..N at [n]) of the field just
/// inside the outer surface (for a homogeneous sphere both are D_n(m x)): Bohren and Huffman
/// eq. 4.88 with D_n / m replaced by H^a_n / m and m D_n by m H^b_n.
void OuterCoefficients(MieCoefficients& c, const std::vector<Complex>& ha,
                       const std::vector<Complex>& hb) {
  const int n_terms = static_cast<int>(ha.size()) - 1;
  const double x = c.x;
  const Complex m = c.m;
  // Riccati-Bessel psi_n(x) = x j_n(x), chi_n(x) = -x y_n(x), xi_n = psi_n - i chi_n, upward.
  double psi0 = std::cos(x), psi1 = std::sin(x);   // psi_{-1}, psi_0
  double chi0 = -std::sin(x), chi1 = std::cos(x);  // chi_{-1}, chi_0
  Complex xi1(psi1, -chi1);
  c.a.resize(n_terms);
  c.b.resize(n_terms);
  for (int n = 1; n <= n_terms; ++n) {
    const double psi = (2.0 * n - 1.0) * psi1 / x - psi0;
    const double chi = (2.0 * n - 1.0) * chi1 / x - chi0;
    const Complex xi(psi, -chi);
    const Complex ta = ha[n] / m + double(n) / x, tb = m * hb[n] + double(n) / x;
    c.a[n - 1] = (ta * psi - psi1) / (ta * xi - xi1);
    c.b[n - 1] = (tb * psi - psi1) / (tb * xi - xi1);
    psi0 = psi1, psi1 = psi;
    chi0 = chi1, chi1 = chi;
    xi1 = xi;
  }
}

/// D3_n(z) = xi_n'(z) / xi_n(z) for n = 0..N from D1 = D_n(z) (Yang 2003):
/// psi_0 xi_0 = (1 - exp(2iz)) / 2, D3_0 = i, psi_n xi_n = psi_{n-1} xi_{n-1} (n / z -
/// D1_{n-1}) (n / z - D3_{n-1}) and D3_n = D1_n + i / (psi_n xi_n).
std::vector<Complex> OutgoingLogDerivatives(Complex z, const std::vector<Complex>& d1) {
  const Complex i(0, 1);
  std::vector<Complex> d3(d1.size());
  Complex psixi = 0.5 * (1.0 - std::exp(2.0 * i * z));
  d3[0] = i;
  for (size_t n = 1; n < d1.size(); ++n) {
    const Complex nz = double(n) / z;
    psixi *= (nz - d1[n - 1]) * (nz - d3[n - 1]);
    d3[n] = d1[n] + i / psixi;
  }
  return d3;
}

}  // namespace

MieCoefficients ComputeMie(Complex m, double x) {
  CheckSize(x);
  CheckIndex(m);
  MieCoefficients c;
  c.m = m;
  c.x = x;
  const std::vector<Complex> dn = LogDerivatives(m * x, MieTerms(x));
  OuterCoefficients(c, dn, dn);
  return c;
}

MieCoefficients ComputeCoatedMie(Complex m_core, double x_core, Complex m_shell, double x) {
  CheckSize(x);
  CheckSize(x_core);
  CheckIndex(m_core);
  CheckIndex(m_shell);
  if (x_core > x)
    throw std::invalid_argument("Mie: the core (x " + std::to_string(x_core) +
                                ") must lie inside the shell (x " + std::to_string(x) + ")");
  MieCoefficients c;
  c.m = m_shell;
  c.x = x;
  c.m_core = m_core;
  c.x_core = x_core;
  const int n_terms = MieTerms(x);
  const Complex z11 = m_core * x_core, z21 = m_shell * x_core, z22 = m_shell * x;
  const std::vector<Complex> d11 = LogDerivatives(z11, n_terms);
  const std::vector<Complex> d21 = LogDerivatives(z21, n_terms);
  const std::vector<Complex> d22 = LogDerivatives(z22, n_terms);
  const std::vector<Complex> d3_21 = OutgoingLogDerivatives(z21, d21);
  const std::vector<Complex> d3_22 = OutgoingLogDerivatives(z22, d22);
  // Q_0 = [psi_0 / xi_0](z21) / [psi_0 / xi_0](z22) with psi_0 / xi_0 = (1 - exp(-2iz)) / 2,
  // written with exp(2iz) so that an absorbing shell (Im z > 0) does not overflow; then
  // [psi_n / xi_n] / [psi_{n-1} / xi_{n-1}] = (D3_n + n / z) / (D1_n + n / z).
  const Complex i(0, 1);
  Complex q = std::exp(2.0 * i * (z22 - z21)) * (std::exp(2.0 * i * z21) - 1.0) /
              (std::exp(2.0 * i * z22) - 1.0);
  std::vector<Complex> ha(n_terms + 1), hb(n_terms + 1);
  for (int n = 1; n <= n_terms; ++n) {
    const Complex n21 = double(n) / z21, n22 = double(n) / z22;
    q *= (d3_21[n] + n21) / (d21[n] + n21) * (d22[n] + n22) / (d3_22[n] + n22);
    // The core's field inside: H = D1_n(m_core x_core); matched at the interface.
    const Complex g1 = m_shell * d11[n] - m_core * d21[n],
                  g2 = m_shell * d11[n] - m_core * d3_21[n];
    const Complex h1 = m_core * d11[n] - m_shell * d21[n],
                  h2 = m_core * d11[n] - m_shell * d3_21[n];
    ha[n] = (g2 * d22[n] - q * g1 * d3_22[n]) / (g2 - q * g1);
    hb[n] = (h2 * d22[n] - q * h1 * d3_22[n]) / (h2 - q * h1);
  }
  OuterCoefficients(c, ha, hb);
  return c;
}

MieEfficiencies Efficiencies(const MieCoefficients& c) {
  MieEfficiencies e;
  Complex back = 0;
  double g = 0;
  const int n_terms = c.terms();
  for (int n = 1; n <= n_terms; ++n) {
    const Complex an = c.a[n - 1], bn = c.b[n - 1];
    const double fn = 2.0 * n + 1.0;
    e.q_ext += fn * (an + bn).real();
    e.q_sca += fn * (std::norm(an) + std::norm(bn));
    back += fn * (n % 2 ? -1.0 : 1.0) * (an - bn);
    g += fn / (n * (n + 1.0)) * (an * std::conj(bn)).real();
    if (n < n_terms) {
      const Complex an1 = c.a[n], bn1 = c.b[n];
      g += n * (n + 2.0) / (n + 1.0) * (an * std::conj(an1) + bn * std::conj(bn1)).real();
    }
  }
  const double x2 = c.x * c.x;
  e.q_ext *= 2 / x2;
  e.q_sca *= 2 / x2;
  e.q_back = std::norm(back) / x2;
  e.g = e.q_sca > 0 ? 4 / (x2 * e.q_sca) * g : 0;
  return e;
}

namespace {
/// S1 and S2 (Bohren and Huffman eq. 4.74) as sums over the terms, with each term's factors
/// (2n + 1) / (n (n + 1)) a_n, b_n and the recurrence's for pi_n computed once. A block of
/// angles is summed term by term across the block: the pi_n recurrence of one angle is a chain
/// of dependent multiplications, and the block's independent chains fill the pipeline (each
/// angle's arithmetic, and so its result, is the same as alone).
class AmplitudeSums {
 public:
  static constexpr int kBlock = 16;

  explicit AmplitudeSums(const MieCoefficients& c)
      : terms_(c.terms()),
        far_(terms_ + 1),
        fai_(terms_ + 1),
        fbr_(terms_ + 1),
        fbi_(terms_ + 1),
        up_(terms_ + 1),
        down_(terms_ + 1) {
    for (int k = 1; k <= terms_; ++k) {
      const double fn = (2.0 * k + 1.0) / (k * (k + 1.0));
      const Complex fa = fn * c.a[k - 1], fb = fn * c.b[k - 1];
      far_[k] = fa.real(), fai_[k] = fa.imag(), fbr_[k] = fb.real(), fbi_[k] = fb.imag();
      up_[k] = (2.0 * k + 1.0) / k, down_[k] = (k + 1.0) / k;
    }
  }

  /// S1, S2 at `count` <= kBlock angles.
  void At(const double* theta, int count, MieAmplitudes* out) const {
    double mu[kBlock], pi0[kBlock], pi1[kBlock];
    double s1r[kBlock], s1i[kBlock], s2r[kBlock], s2i[kBlock];
    for (int l = 0; l < kBlock; ++l) {
      mu[l] = std::cos(theta[std::min(l, count - 1)]);
      pi0[l] = 0, pi1[l] = 1;  // pi_{n-1}, pi_n
      s1r[l] = s1i[l] = s2r[l] = s2i[l] = 0;
    }
    for (int k = 1; k <= terms_; ++k) {
      const double ar = far_[k], ai = fai_[k], br = fbr_[k], bi = fbi_[k];
      const double kk = k, k1 = k + 1, up = up_[k], down = down_[k];
      for (int l = 0; l < kBlock; ++l) {
        const double tau = kk * mu[l] * pi1[l] - k1 * pi0[l];
        s1r[l] += ar * pi1[l] + br * tau;
        s1i[l] += ai * pi1[l] + bi * tau;
        s2r[l] += ar * tau + br * pi1[l];
        s2i[l] += ai * tau + bi * pi1[l];
        const double pi2 = up * mu[l] * pi1[l] - down * pi0[l];  // pi_{n+1}
        pi0[l] = pi1[l], pi1[l] = pi2;
      }
    }
    for (int l = 0; l < count; ++l) out[l] = {{s1r[l], s1i[l]}, {s2r[l], s2i[l]}};
  }

  MieAmplitudes At(double theta) const {
    MieAmplitudes s;
    At(&theta, 1, &s);
    return s;
  }

 private:
  int terms_;
  std::vector<double> far_, fai_, fbr_, fbi_;
  std::vector<double> up_, down_;
};
}  // namespace

MieAmplitudes Amplitudes(const MieCoefficients& c, double theta) {
  return AmplitudeSums(c).At(theta);
}

MieTable::MieTable(const MieCoefficients& c, double theta_max, double step_per_x) {
  theta_max_ = std::min(theta_max, M_PI);
  step_ = std::min(step_per_x / std::max(c.x, 1e-3), 0.01);
  // Nodes from -step to theta_max + 2 steps so every query has two nodes on each side; S is
  // even in theta (pi_n, tau_n are functions of cos theta), so the node at -step is S(step).
  const int n = static_cast<int>(std::ceil(theta_max_ / step_)) + 4;
  s1_.resize(n);
  s2_.resize(n);
  const AmplitudeSums sums(c);
  const int blocks = (n + AmplitudeSums::kBlock - 1) / AmplitudeSums::kBlock;
  tbb::parallel_for(0, blocks, [&](int b) {  // each node on its own: the same for any threads
    const int i0 = b * AmplitudeSums::kBlock, count = std::min(AmplitudeSums::kBlock, n - i0);
    double theta[AmplitudeSums::kBlock];
    MieAmplitudes s[AmplitudeSums::kBlock];
    for (int l = 0; l < count; ++l) theta[l] = std::abs((i0 + l - 1) * step_);
    sums.At(theta, count, s);
    for (int l = 0; l < count; ++l) s1_[i0 + l] = s[l].s1, s2_[i0 + l] = s[l].s2;
  });
}

MieAmplitudes MieTable::At(double theta) const {
  const double t = std::clamp(theta, 0.0, theta_max_) / step_ + 1;  // node index coordinate
  const int i = std::clamp(static_cast<int>(t), 1, static_cast<int>(s1_.size()) - 3);
  const double u = t - i;  // in [0, 1) between nodes i and i + 1
  // Lagrange weights on nodes i-1, i, i+1, i+2 at offsets -1, 0, 1, 2.
  const double w0 = -u * (u - 1) * (u - 2) / 6, w1 = (u + 1) * (u - 1) * (u - 2) / 2;
  const double w2 = -(u + 1) * u * (u - 2) / 2, w3 = (u + 1) * u * (u - 1) / 6;
  return {w0 * s1_[i - 1] + w1 * s1_[i] + w2 * s1_[i + 1] + w3 * s1_[i + 2],
          w0 * s2_[i - 1] + w1 * s2_[i] + w2 * s2_[i + 1] + w3 * s2_[i + 2]};
}

}  // namespace raymatch::simulate
