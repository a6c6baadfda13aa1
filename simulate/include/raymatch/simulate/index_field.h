#pragma once
// Refractive-index fields inside an object (gradient-index media) and the ray integrator.
//
// Coordinates are object-local: p_local = p_world - object centre (micrometres); the symmetry
// axis of axisymmetric fields is the local z axis. Grids are interpolated bilinearly (r, z) or
// trilinearly (x, y, z): the interpolant never overshoots, so at a jump (a shock front) the index
// stays between the two sides and changes within one cell; its gradient is constant per cell.
// Outside the grid's domain the nearest grid value is used (constant extrapolation).
#include <memory>
#include <string>
#include <vector>

#include "raymatch/core/vec.h"

namespace raymatch::simulate {

enum class IndexFieldType { kLuneburg, kFishEye, kParabolic, kLinearN2, kGridRZ, kGrid3D };

class IndexField {
 public:
  IndexFieldType type = IndexFieldType::kLuneburg;
  // Analytic parameters (REFERENCE.md section 5):
  double n0 = 1.0;        ///< Luneburg: index at the surface (n = n0 sqrt(2 - (r/R)^2));
                          ///< fish-eye: centre index; parabolic: axis index; linear n^2: at origin
  double radius_um = 1;   ///< Luneburg R, fish-eye a
  double g_per_um = 0;    ///< parabolic gradient constant g
  Vec3 k_per_um;          ///< linear n^2: n^2 = n0^2 + k . p
  // Grids: values[iz][ir] (rz) or values[iz][iy][ix] (3D), C order.
  std::vector<double> values;
  int nx = 0, ny = 0, nz = 0;   ///< rz: nx = number of r samples, ny = 1
  Vec3 origin_um;               ///< local coordinates of sample (0, 0, 0); rz: (r0, -, z0)
  Vec3 spacing_um;              ///< rz: (dr, -, dz)
  double min_n = 1, max_n = 1;  ///< range of the field (for reports and checks)
  std::string description;

  /// Index and its gradient at a local point.
  void Eval(const Vec3& p, double* n, Vec3* grad_n) const;
  double Index(const Vec3& p) const {
    double n;
    Vec3 g;
    Eval(p, &n, &g);
    return n;
  }
  /// Largest step the integrator may take (half the finest grid spacing; 0 = no cap).
  double MaxStepUm() const;
};

/// Tolerances for the gradient-index integrator.
struct GrinSettings {
  double tolerance_um = 1e-5;   ///< position error allowed per step (step doubling estimate)
  double max_step_um = 0;       ///< cap on the step length (0: the field's own cap, else none)
  int max_steps = 2000000;      ///< per ray segment; beyond it the ray ends (interaction_cap)
};

/// Ray state in a gradient-index medium: position R and optical direction T = n dR/ds.
struct GrinState {
  Vec3 r, t;
};

/// One Sharma-Kumar-Ghatak step (Appl. Opt. 21, 984 (1982)) with parameter dt = ds / n;
/// fourth order, exact when n^2 is linear in position. `center` maps world to local.
GrinState SharmaStep(const IndexField& f, const Vec3& center, const GrinState& s, double dt);

/// Adaptive integration: advances `s` by one accepted step of at most `*dt`; `*used` receives
/// the parameter step taken and `*dt` the controller's next proposal (step doubling, error per
/// step <= cfg.tolerance_um). Returns the number of field evaluations used.
int AdaptiveStep(const IndexField& f, const Vec3& center, const GrinSettings& cfg, GrinState* s,
                 double* dt, double* used);

}  // namespace raymatch::simulate
