#pragma once
// Shapes built from data: surfaces of revolution from a 2D outline (points or a silhouette
// image, the paper's first method for merging drops), iso-surfaces of CFD volume-fraction grids,
// and checks that a triangle mesh encloses a volume.
#include <array>
#include <string>
#include <vector>

#include "raymatch/core/array_io.h"
#include "raymatch/core/image.h"
#include "raymatch/core/vec.h"

namespace raymatch::simulate {

struct TriangleMesh {
  std::vector<Vec3> vertices;  ///< object-local micrometres
  std::vector<std::array<unsigned, 3>> triangles;
};

/// An outline of a body of revolution: (r, z) pairs in micrometres, ordered from one pole to
/// the other along the local z axis (r >= 0).
using Outline = std::vector<std::array<double, 2>>;

/// Revolves an outline about the local z axis into a closed triangle mesh with `segments`
/// facets around. Ends off the axis are closed with flat caps. Throws Error on fewer than two
/// points, negative radii or a non-finite value.
TriangleMesh RevolveOutline(const Outline& outline, int segments);

/// Options for extracting an outline from a silhouette image (the object darker than the
/// background, as a transparent drop in brightfield is at its rim).
struct SilhouetteOptions {
  double pixel_um = 1;        ///< pixel size at the object plane
  double threshold = 0.5;     ///< between the darkest pixel (0) and the background median (1)
  bool vertical_axis = true;  ///< the axis of revolution runs along image columns (up = +z)
  double axis_px = -1;        ///< position of the axis in pixels (column or row); <0 = fitted
  double smooth_px = 1.5;     ///< Gaussian smoothing of r(z) along the axis, in pixels
};

/// Outline from the largest dark blob of an image (OpenCV contours, holes filled): for each row
/// (or column) across the axis, r = half the blob's width about the axis; z = 0 at the blob's
/// centre along the axis. Throws Error if no blob is found.
Outline OutlineFromSilhouette(const Image& image, const SilhouetteOptions& options,
                              double* fitted_axis_px = nullptr);

/// Reads an outline from a CSV file of "r_um,z_um" lines (a header line is allowed).
Outline ReadOutlineCsv(const std::string& path);

/// Iso-surface of a volume-fraction grid [nz][ny][nx] (1 = liquid) at `iso` (0.5 by default),
/// via OpenVDB's volumeToMesh; `spacing_um` and `origin_um` place sample (0,0,0).
TriangleMesh MeshFromVolumeFraction(const NdArray& fraction, const Vec3& spacing_um,
                                    const Vec3& origin_um, double iso);

/// What CheckMesh found; a mesh is usable when it is closed and does not cross itself.
struct MeshReport {
  size_t triangles = 0;
  size_t degenerate_removed = 0;  ///< zero-area triangles dropped
  size_t open_edges = 0;          ///< edges used by one triangle only (holes)
  size_t nonmanifold_edges = 0;   ///< edges used by more than two triangles
  size_t self_intersections = 0;  ///< triangle edges piercing another triangle
  double signed_volume_um3 = 0;
  bool flipped = false;  ///< winding was inward and was reversed
  bool ok() const { return open_edges == 0 && nonmanifold_edges == 0 && self_intersections == 0; }
  std::string Summary() const;
};

/// Drops degenerate triangles, makes the winding outward, and checks watertightness (every
/// edge shared by exactly two triangles) and self-intersection (each edge tested against an
/// Embree BVH of the other triangles). Modifies `mesh`.
MeshReport CheckAndOrientMesh(TriangleMesh* mesh);

}  // namespace raymatch::simulate
