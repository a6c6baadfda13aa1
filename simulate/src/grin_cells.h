#pragma once
// The gradient-index integrator's cell-by-cell stepping on 3D grids (index_field.cpp), for the
// tracer's objects stage: internals, not part of the library's interface (index_field.h).
#include <limits>

#include "raymatch/simulate/index_field.h"

namespace raymatch::simulate {

/// The integrator's two cells: the one the current point is in, and a spare in which the next
/// one is built while a step is computed (CellStep swaps them; nothing is copied).
struct GridCellPair {
  GridCell cell[2];
  int current = 0;
  const GridCell& now() const { return cell[current]; }
};

/// How far past a face a step that ends on it lands (in cells): the next step starts in the
/// next cell. The field the step used there is the previous cell's polynomial; the error that
/// makes in the direction is |jump of grad n| x this distance.
constexpr double kCellOvershoot = 1e-9;

/// Where a ray leaves a grid cell (GridCell): the parameter step (ds = n dt) to a point
/// kCellOvershoot past the face it meets first, and that face.
struct CellExit {
  double dt = std::numeric_limits<double>::infinity();  ///< +inf: through no face
  int axis = -1;                                        ///< 0, 1, 2 for x, y, z
  int side = 0;                                         ///< +1: the face at `hi`, -1: at `lo`
};
/// The exit predicted from the path p + t dt + d dt^2 / 2 (local point p, optical direction t,
/// D = n grad n at p).
CellExit PredictCellExit(const GridCell& cell, const Vec3& p, const Vec3& t, const Vec3& d);

/// The same for a 3D grid, one cell at a time (GrinSettings::cell_steps): the step ends just
/// past the face of `*cell` that the ray meets first (or earlier, if the tolerance says so),
/// its inner stages use the cell's polynomial, and cells->now() becomes the cell of the step's
/// end. It is located afresh when it was not located from s->r (its `at` differs).
int CellStep(const IndexField& f, const Vec3& center, const GrinSettings& cfg, GridCellPair* cells,
             GrinPoint* s, double* dt, double* used);
}  // namespace raymatch::simulate
