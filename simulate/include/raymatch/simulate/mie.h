#pragma once
// Mie theory: the exact scattering of a plane wave by a homogeneous sphere.
//
// Conventions (Bohren and Huffman, *Absorption and Scattering of Light by Small Particles*,
// Wiley 1983, ch. 4): time dependence exp(-i omega t), so an absorbing sphere has a relative
// index m = n + i k with k >= 0; the size parameter x = 2 pi n_medium a / lambda (lambda in
// vacuum); the scattered far field of an incident field E_i (amplitude at the sphere's centre) is
//   E_par_s = exp(ikr) / (-ikr) S2(theta) E_par_i,   E_perp_s = exp(ikr) / (-ikr) S1(theta)
//   E_perp_i
// with the parallel / perpendicular components taken in the scattering plane. Efficiencies are
// cross sections over pi a^2.
//
// Numerics (W. J. Wiscombe, "Improved Mie scattering algorithms", Appl. Opt. 19, 1505 (1980)):
// N = round(x + 4.05 x^(1/3) + 2) terms; the logarithmic derivative D_n(m x) by downward
// recurrence started from Lentz's continued fraction (W. J. Lentz, Appl. Opt. 15, 668 (1976)),
// stable for any |m x|; the Riccati-Bessel functions of the real argument x by upward
// recurrence, stable up to N.
#include <complex>
#include <vector>

namespace raymatch::simulate {

using Complex = std::complex<double>;

/// The Mie coefficients a_n, b_n (n = 1..N, stored at [n - 1]) of a sphere.
struct MieCoefficients {
  Complex m;  ///< relative index n_sphere / n_medium (imaginary part >= 0: absorbing)
  double x = 0;
  Complex m_core;     ///< a coated sphere's core index relative to the medium (else 0)
  double x_core = 0;  ///< its size parameter 2 pi n_medium a_core / lambda (0: homogeneous)
  std::vector<Complex> a, b;
  int terms() const { return static_cast<int>(a.size()); }
};

/// The number of terms Wiscombe (1980) prescribes, round(x + 4.05 x^(1/3) + 2).
int MieTerms(double x);

/// Mie coefficients of a homogeneous sphere of relative index `m` and size parameter `x`.
/// Throws std::invalid_argument for x <= 0, Im m < 0 or Re m <= 0.
MieCoefficients ComputeMie(Complex m, double x);

/// Mie coefficients of a concentric coated sphere: a core of relative index `m_core` and size
/// parameter `x_core` inside a shell of `m_shell` whose outer size parameter is `x` (the
/// coefficients' m and x are the shell's). The recursion of W. Yang, "Improved recursive
/// algorithm for light scattering by a multilayered sphere", Appl. Opt. 42, 1710 (2003): each
/// interface carries the logarithmic derivatives H^a_n, H^b_n of the field inside it outwards,
/// with the ratio Q_n = [psi_n / xi_n](m_shell x_core) / [psi_n / xi_n](m_shell x) by upward
/// recurrence from Q_0 and D3_n = xi_n' / xi_n from the products psi_n xi_n, so no Bessel
/// function of the complex arguments is formed; D1_n as for a homogeneous sphere. N terms as
/// for the outer size parameter. Equal indices give the homogeneous sphere's coefficients.
/// Throws std::invalid_argument unless 0 < x_core <= x and both indices are valid.
MieCoefficients ComputeCoatedMie(Complex m_core, double x_core, Complex m_shell, double x);

/// Efficiencies and asymmetry parameter (Bohren and Huffman eqs. 4.61, 4.62, 4.82 and p. 120).
struct MieEfficiencies {
  double q_ext = 0, q_sca = 0, q_back = 0, g = 0;
};
MieEfficiencies Efficiencies(const MieCoefficients& c);

/// The amplitude-matrix elements at one scattering angle (radians, from the incident direction).
struct MieAmplitudes {
  Complex s1, s2;
};
MieAmplitudes Amplitudes(const MieCoefficients& c, double theta);

/// S1 and S2 tabulated on a uniform grid of scattering angle from 0 to `theta_max` and
/// interpolated by 4-point Lagrange cubics: the step is `step_per_x` / x radians, a small fraction
/// of the period (about 2 pi / (2 x)) of the amplitudes' fastest oscillation, so the
/// interpolation error falls as (x step)^4 (about 1e-5 of |S| at the default 0.05).
class MieTable {
 public:
  MieTable() = default;
  MieTable(const MieCoefficients& c, double theta_max, double step_per_x = 0.05);
  /// S1, S2 at `theta` in [0, theta_max] (clamped).
  MieAmplitudes At(double theta) const;
  double theta_max() const { return theta_max_; }
  double step() const { return step_; }

 private:
  double theta_max_ = 0, step_ = 1;
  std::vector<Complex> s1_, s2_;  // values at the nodes
};

}  // namespace raymatch::simulate
