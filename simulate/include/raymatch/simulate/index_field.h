#pragma once
// Refractive-index fields inside an object (gradient-index media) and the ray integrator.
//
// Coordinates are object-local: p_local = p_world - object centre (micrometres); the symmetry
// axis of axisymmetric fields is the local z axis. Grids are interpolated bilinearly (r, z) or
// trilinearly (x, y, z): the interpolant never overshoots, so at a jump (a shock front) the index
// stays between the two sides and changes within one cell; its gradient is constant per cell.
// Outside the grid's domain the nearest grid value is used (constant extrapolation).
#include <cstdint>
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
  double tolerance_um = 1e-5;   ///< position error allowed per step (embedded error estimate)
  double max_step_um = 0;       ///< cap on the step length (0: the field's own cap, else none)
  int max_steps = 2000000;      ///< per ray segment; beyond it the ray ends (interaction_cap)
  /// Grid fields: cross runs of cells whose corner values differ by at most this (index units)
  /// in one straight step; < 0 turns it off. The deflection neglected is below
  /// tolerance x path / spacing (1e-10 rad over 100 um at 0.1 um spacing for the default).
  double uniform_tolerance = 1e-13;
  /// The former controller (step doubling of Sharma steps, 11 field evaluations per accepted
  /// step against 3): kept for comparisons in benchmarks; same tolerance meaning.
  bool step_doubling = false;
};

/// Ray state in a gradient-index medium: position R and optical direction T = n dR/ds.
struct GrinState {
  Vec3 r, t;
};

/// One Sharma-Kumar-Ghatak step (Appl. Opt. 21, 984 (1982)) with parameter dt = ds / n;
/// fourth order, exact when n^2 is linear in position. `center` maps world to local.
GrinState SharmaStep(const IndexField& f, const Vec3& center, const GrinState& s, double dt);

/// Integrator state plus the field at r: its index n and D = n grad n = grad(n^2)/2, which is
/// also the first stage of the next step (first same as last: 3 evaluations per step).
struct GrinPoint {
  Vec3 r, t, d;
  double n = 1;
};
/// The point at `r` with optical direction along `t`, rescaled so that |T| = n(r).
GrinPoint MakeGrinPoint(const IndexField& f, const Vec3& center, const Vec3& r, const Vec3& t);

/// One Sharma step from a GrinPoint (2 new evaluations inside the step, 1 at its end), |T|
/// renormalised to n at the end. `err` (optional) receives the embedded error estimate.
GrinPoint SharmaStep(const IndexField& f, const Vec3& center, const GrinPoint& s, double dt,
                     double* err = nullptr);

/// Adaptive integration: advances `s` by one accepted step of at most `*dt`; `*used` receives
/// the parameter step taken and `*dt` the controller's next proposal (position error per step
/// <= cfg.tolerance_um). The error estimate is embedded: Sharma's stages at c = (0, 1/2, 1)
/// also give a third-order position (weights 1/3, 0, 1/6 against the fourth-order 1/6, 1/3,
/// 0), and their difference |A - 2B + C| dt / 6 bounds the step's error (the fourth-order
/// result is kept: local extrapolation). Returns the number of field evaluations used.
int AdaptiveStep(const IndexField& f, const Vec3& center, const GrinSettings& cfg, GrinPoint* s,
                 double* dt, double* used);
/// The same from a bare state (computes the first stage).
int AdaptiveStep(const IndexField& f, const Vec3& center, const GrinSettings& cfg, GrinState* s,
                 double* dt, double* used);

/// Where a grid field is uniform, for straight steps across it: per block of 4^3 grid cells, the
/// Chebyshev distance in blocks to the nearest block holding a cell whose corner values differ
/// by more than a tolerance (or to the grid's edge). Empty for analytic fields.
class UniformCells {
 public:
  UniformCells() = default;
  UniformCells(const IndexField& f, double tolerance);
  bool empty() const { return dist_.empty(); }
  /// Length of any straight path from local point p that stays in uniform cells (0: p is not
  /// in one).
  double FreeLength(const Vec3& p) const;
  size_t uniform_cells() const { return uniform_cells_; }  ///< grid cells in uniform blocks
  static constexpr int kBlock = 4;  ///< cells per block side (the map's resolution)

 private:
  bool rz_ = false;
  int cx_ = 0, cy_ = 0, cz_ = 0;  // cells per axis (rz: cx_ along r, cy_ = 1)
  Vec3 origin_, spacing_, inv_spacing_;
  std::vector<uint8_t> dist_;
  size_t uniform_cells_ = 0;
};

}  // namespace raymatch::simulate
