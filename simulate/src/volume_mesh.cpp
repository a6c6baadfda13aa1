// Iso-surfaces of CFD volume-fraction grids through OpenVDB (tools::volumeToMesh).
#include <openvdb/openvdb.h>
#include <openvdb/tools/VolumeToMesh.h>

#include <cmath>

#include "raymatch/core/error.h"
#include "raymatch/simulate/shapes.h"

namespace raymatch::simulate {

TriangleMesh MeshFromVolumeFraction(const NdArray& f, const Vec3& spacing, const Vec3& origin,
                                    double iso) {
  if (f.shape.size() != 3) throw Error("a volume-fraction grid must be a 3D array [nz][ny][nx]");
  const size_t nz = f.shape[0], ny = f.shape[1], nx = f.shape[2];
  openvdb::initialize();
  // Background 0 (no liquid) outside the grid closes surfaces that touch its faces.
  openvdb::FloatGrid::Ptr grid = openvdb::FloatGrid::create(0.0f);
  auto acc = grid->getAccessor();
  size_t above = 0;
  for (size_t k = 0; k < nz; ++k)
    for (size_t j = 0; j < ny; ++j)
      for (size_t i = 0; i < nx; ++i) {
        const double v = f.values[(k * ny + j) * nx + i];
        if (!std::isfinite(v)) throw Error("volume-fraction grid has NaN or Inf values");
        above += v > iso;
        if (v != 0) acc.setValue(openvdb::Coord(int(i), int(j), int(k)), float(v));
      }
  if (above == 0) throw Error("no grid value exceeds the iso level " + std::to_string(iso));
  std::vector<openvdb::Vec3s> points;
  std::vector<openvdb::Vec3I> tris;
  std::vector<openvdb::Vec4I> quads;
  openvdb::tools::volumeToMesh(*grid, points, tris, quads, iso, 0.0);
  TriangleMesh m;
  for (const auto& p : points)
    m.vertices.push_back(
        {origin.x + p.x() * spacing.x, origin.y + p.y() * spacing.y, origin.z + p.z() * spacing.z});
  for (const auto& t : tris) m.triangles.push_back({t.x(), t.y(), t.z()});
  for (const auto& q : quads) {
    m.triangles.push_back({q.x(), q.y(), q.z()});
    m.triangles.push_back({q.x(), q.z(), q.w()});
  }
  return m;
}

}  // namespace raymatch::simulate
