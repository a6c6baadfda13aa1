// libFuzzer harness: mesh files (OBJ, STL and PLY read by Assimp, then raymatch's own checks:
// declared sizes against the file, face indices, finite vertices, closed and oriented surface,
// simulate/src/geometry.cpp), through simulate::Geometry as a scene's mesh object uses them.
// The input's content picks the extension, as a user's file name would: "ply" first -> .ply,
// "solid" first or a NUL byte in the first 84 (a binary STL header) -> .stl, else .obj. A
// harness passes when the mesh is built (with a finite volume and at least one triangle) or
// refused with a raymatch::Error.
#include <cstring>

#include "fuzz_input.h"
#include "raymatch/simulate/geometry.h"
#include "raymatch/simulate/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::string dir = raymatch::fuzz::ScratchFolder("mesh", {});
  std::string ext = ".obj";
  if (size >= 3 && std::memcmp(data, "ply", 3) == 0)
    ext = ".ply";
  else if ((size >= 5 && std::memcmp(data, "solid", 5) == 0) ||
           std::memchr(data, 0, std::min<size_t>(size, 84)))
    ext = ".stl";
  // A new name per input: the mesh cache (keyed by path, size and modification time, whose
  // clock is coarse) must not answer for an earlier input.
  static unsigned long n = 0;
  const std::string path = dir + "/mesh" + std::to_string(n++) + ext;
  raymatch::fuzz::WriteInputTo(path, data, size);
  raymatch::simulate::ObjectSpec o;
  o.shape = raymatch::simulate::ShapeType::kMesh;
  o.mesh_file = path;
  o.mesh_scale_um = 10;
  o.where = raymatch::FileLocation{"fuzz-scene.toml", 1, 1};
  const int rc = raymatch::fuzz::Expect([&] {
    const raymatch::simulate::Geometry g({o});
    for (const auto& m : g.meshes()) {
      raymatch::fuzz::CheckFinite(m.signed_volume_um3, "mesh volume");
      if (m.triangles == 0) raymatch::fuzz::CheckFinite(NAN, "a built mesh has triangles");
    }
    raymatch::fuzz::CheckFinite(g.extent_um(), "mesh extent");
  });
  std::filesystem::remove(path);
  return rc;
}
