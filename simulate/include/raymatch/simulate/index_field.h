#pragma once
// Refractive-index fields inside an object (gradient-index media) and the ray integrator.
//
// Coordinates are object-local: p_local = p_world - object centre (micrometres); the symmetry
// axis of axisymmetric fields is the local z axis. Grids are interpolated bilinearly (r, z) or
// trilinearly (x, y, z): the interpolant never overshoots, so at a jump (a shock front) the index
// stays between the two sides and changes within one cell; its gradient is constant per cell.
// Outside the grid's domain the nearest grid value is used (constant extrapolation).
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "raymatch/core/vec.h"

namespace raymatch::simulate {

enum class IndexFieldType { kLuneburg, kFishEye, kParabolic, kLinearN2, kGridRZ, kGrid3D };

/// The trilinear interpolant of a 3D grid on one cell, as a polynomial in the cell's fractional
/// coordinates (u, v, w) = (p - node) / spacing:
///   n = c0 + c1 u + c2 v + c3 w + c4 uv + c5 uw + c6 vw + c7 uvw.
/// Beyond the grid's edge along an axis (and along an axis with a single sample) the field holds
/// its edge value: that axis's terms vanish and the cell reaches to infinity along it. The
/// integrator evaluates every stage of a step with the polynomial of the cell the step starts in
/// (IndexField::EvalInCell), so a step that ends on a face sees a smooth field.
struct GridCell {
  Vec3 at{NAN, NAN, NAN};  ///< the local point it was located from (the integrator's cache key)
  Vec3 node;               ///< local coordinates of the cell's first node (where u = v = w = 0)
  Vec3 inv_spacing;        ///< 1 / spacing per axis
  double lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};  ///< extent in u, v, w (+-inf beyond the edge)
  double c[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  /// Cell index per axis: 0 ... count - 2 between samples, -1 before the first sample, count - 1
  /// beyond the last (an axis with a single sample has only -1 and 0, both unbounded).
  int k[3] = {0, 0, 0};
  size_t base = 0;               ///< values index of the node at `node`
  size_t stride[3] = {0, 0, 0};  ///< values index steps to the other corners (0: constant axis)
};

class IndexField {
 public:
  IndexFieldType type = IndexFieldType::kLuneburg;
  // Analytic parameters (the classic exact GRIN media; Sharma, Kumar, Ghatak, Appl. Opt. 21, 984
  // (1982)):
  double n0 = 1.0;       ///< Luneburg: index at the surface (n = n0 sqrt(2 - (r/R)^2));
                         ///< fish-eye: centre index; parabolic: axis index; linear n^2: at origin
  double radius_um = 1;  ///< Luneburg R, fish-eye a
  double g_per_um = 0;   ///< parabolic gradient constant g
  Vec3 k_per_um;         ///< linear n^2: n^2 = n0^2 + k . p
  // Grids: values[iz][ir] (rz) or values[iz][iy][ix] (3D), C order.
  std::vector<double> values;
  int nx = 0, ny = 0, nz = 0;   ///< rz: nx = number of r samples, ny = 1
  Vec3 origin_um;               ///< local coordinates of sample (0, 0, 0); rz: (r0, -, z0)
  Vec3 spacing_um;              ///< rz: (dr, -, dz)
  double min_n = 1, max_n = 1;  ///< range of the field (for reports and checks)
  std::string description;
  /// Water density grids (quantity = "density"): the wavelength their index values were computed
  /// at and a subsample of the grid's states, so that a ray of another wavelength sees the field
  /// at its own (WaterIndexMap, AffineView). Null for other fields.
  struct WaterStates {
    double wavelength_um = 0;
    std::vector<double> density_kg_m3, temperature_K;
  };
  std::shared_ptr<const WaterStates> water;
  /// The field rotated about its object's centre (`rotation_deg`, R = Rz Ry Rx as for objects):
  /// the index at local point p is the unrotated field's at R^T p, its gradient rotated by R.
  /// Set whenever the scene gives `rotation_deg`, even [0, 0, 0], so that a fit of the angles
  /// traces every evaluation with the same integrator (a rotated 3D grid is not stepped cell by
  /// cell: its cells are not aligned with the local axes).
  bool rotated = false;
  Mat3 rotation, rotation_t;

  /// A grid field's view that shares this grid (not a copy; it must outlive the view) and gives
  /// offset + scale x its index, gradient scaled alike (SetMap; initially offset 0, scale 1).
  IndexField AffineView() const;
  void SetMap(double offset, double scale) { map_offset_ = offset, map_scale_ = scale; }

  /// Index and its gradient at a local point.
  void Eval(const Vec3& p, double* n, Vec3* grad_n) const {
    if (!rotated) return EvalUnrotated(p, n, grad_n);
    Vec3 g;
    EvalUnrotated(rotation_t * p, n, &g);
    *grad_n = rotation * g;
  }
  double Index(const Vec3& p) const {
    double n;
    Vec3 g;
    Eval(p, &n, &g);
    return n;
  }
  /// Largest step the integrator may take (half the finest grid spacing; 0 = no cap); 3D grids
  /// stepped cell by cell are capped at the cell's diagonal instead.
  double MaxStepUm() const;
  /// 3D grids: the cell that holds local point p (on a face: the cell beyond it).
  GridCell Cell(const Vec3& p) const;
  /// The same with the reciprocal spacings given (the integrator's cells share them).
  GridCell CellWith(const Vec3& p, const Vec3& inv_spacing) const;
  /// The cell beyond the face of `cell` on `axis` at side +1 (hi) or -1 (lo), into *next; its
  /// `at` is left unset.
  void NextCell(const GridCell& cell, int axis, int side, GridCell* next) const;
  /// 3D grids: the interpolant of `cell` (extended as a polynomial) and its gradient at p.
  static void EvalInCell(const GridCell& cell, const Vec3& p, double* n, Vec3* grad_n);

 private:
  void EvalUnrotated(const Vec3& p, double* n, Vec3* grad_n) const;  ///< in the field's own axes
  void Fill(GridCell* cell) const;     ///< node, extent, strides and corners from cell->k
  void Corners(GridCell* cell) const;  ///< coefficients from cell->base and cell->stride
  const double* grid() const { return shared_ ? shared_ : values.data(); }
  const double* shared_ = nullptr;  // a view's grid (AffineView)
  bool mapped_ = false;             // a view: values pass through the map
  double map_offset_ = 0, map_scale_ = 1;
};

inline void IndexField::EvalInCell(const GridCell& g, const Vec3& p, double* n, Vec3* grad) {
  const double u = (p.x - g.node.x) * g.inv_spacing.x, v = (p.y - g.node.y) * g.inv_spacing.y,
               w = (p.z - g.node.z) * g.inv_spacing.z;
  const double* c = g.c;
  const double vw = v * w;
  const double gu = c[1] + c[4] * v + c[5] * w + c[7] * vw;
  const double gv = c[2] + c[4] * u + c[6] * w + c[7] * (u * w);
  const double gw = c[3] + c[5] * u + c[6] * v + c[7] * (u * v);
  *n = c[0] + c[2] * v + c[3] * w + c[6] * vw + u * gu;
  *grad = Vec3(gu * g.inv_spacing.x, gv * g.inv_spacing.y, gw * g.inv_spacing.z);
}

/// Tolerances for the gradient-index integrator.
struct GrinSettings {
  double tolerance_um = 1e-5;  ///< position error allowed per step (embedded error estimate)
  double max_step_um = 0;      ///< cap on the step length (0: the field's own cap, else none)
  int max_steps = 2000000;     ///< per ray segment; beyond it the ray ends (grin_step_cap)
  /// Grid fields: cross runs of cells whose corner values differ by at most this (index units)
  /// in one straight step; < 0 turns it off. The deflection neglected is below
  /// tolerance x path / spacing (1e-10 rad over 100 um at 0.1 um spacing for the default).
  double uniform_tolerance = 1e-13;
  /// 3D grids: steps end on cell faces (just past them), so that no step straddles the jump of
  /// the interpolant's gradient at a face, and are capped at the diagonal of a cell (not half the
  /// size of a cell). Off: steps may straddle faces, capped at half a cell.
  bool cell_steps = true;
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
/// Whether a field is integrated with CellStep under these settings (3D grids not rotated, cell
/// steps on, the embedded controller).
inline bool UsesCellSteps(const IndexField& f, const GrinSettings& cfg) {
  return cfg.cell_steps && !cfg.step_doubling && f.type == IndexFieldType::kGrid3D && !f.rotated;
}
/// The same from a bare state (computes the first stage).
int AdaptiveStep(const IndexField& f, const Vec3& center, const GrinSettings& cfg, GrinState* s,
                 double* dt, double* used);

/// Where a grid field is uniform, for straight steps across it: per block of B^3 grid cells, the
/// Chebyshev distance in blocks to the nearest block holding a cell whose corner values differ
/// by more than a tolerance (or to the grid's edge). Empty for analytic fields.
class UniformCells {
 public:
  UniformCells() = default;
  /// `block`: cells per block side B; 0 chooses the smallest of 1, 2, 4 whose map has at most
  /// kMaxBlocks entries.
  UniformCells(const IndexField& f, double tolerance, int block = 0);
  bool empty() const { return dist_.empty(); }
  /// Length of any straight path from local point p that stays in uniform cells (0: p is not
  /// in one).
  double FreeLength(const Vec3& p) const;
  size_t uniform_cells() const { return uniform_cells_; }  ///< grid cells in uniform blocks
  int block() const { return block_; }                     ///< cells per block side
  static constexpr size_t kMaxBlocks = size_t(1) << 18;    ///< the automatic block's map size

 private:
  bool rz_ = false;
  int block_ = 4;
  bool rotated_ = false;  // the field's rotation_t (R^T) maps local points into its axes
  Mat3 rotation_t_;
  int cx_ = 0, cy_ = 0, cz_ = 0;  // cells per axis (rz: cx_ along r, cy_ = 1)
  Vec3 origin_, spacing_, inv_spacing_;
  std::vector<uint8_t> dist_;
  size_t uniform_cells_ = 0;
};

}  // namespace raymatch::simulate
