#include "raymatch/simulate/geometry.h"

#include <assimp/postprocess.h>
#include <assimp/scene.h>
#include <embree3/rtcore.h>

#include <assimp/Importer.hpp>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <list>
#include <memory>
#include <mutex>
#include <sstream>
#include <stdexcept>

#include "raymatch/core/error.h"
#include "raymatch/simulate/shapes.h"

// Debian's Assimp 5.2 is built with its internal assertions on, and a failed one calls abort():
// a corrupt ASCII PLY whose face lines run into other text aborted inside the post-processing
// (found by scripts/fuzz.sh mesh). This definition takes the place of the library's (the
// executable's symbol interposes on the shared library's) and turns the assertion into an
// error, which LocalMesh reports naming the mesh file.
namespace Assimp {
void aiAssertViolation(const char* expression, const char* file, int line) {
  throw std::runtime_error(std::string("Assimp's internal check '") +
                           (expression ? expression : "?") + "' failed (" + (file ? file : "?") +
                           ":" + std::to_string(line) + ")");
}
}  // namespace Assimp

namespace raymatch::simulate {

namespace {

// Leaving a surface: offset the new origin by this fraction of the object's size. Analytic
// shapes are solved in double (relative error ~1e-15), Embree in float (~1e-7), hence two scales.
constexpr double kAnalyticEpsilon = 1e-9;
constexpr double kMeshEpsilon = 2e-5;

bool IsStlFile(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return ext == ".stl";
}

// Declared element counts in a PLY or binary STL header must fit in the file before Assimp
// allocates for them: every PLY element takes at least one byte, every binary STL triangle 50.
void CheckMeshFileSizes(const ObjectSpec& o) {
  std::error_code ec;
  const uintmax_t size = std::filesystem::file_size(o.mesh_file, ec);
  if (ec) throw Error(o.where, "cannot read mesh '" + o.mesh_file + "': " + ec.message());
  constexpr uintmax_t kMaxMeshBytes = uintmax_t(2) << 30;
  if (size > kMaxMeshBytes)
    throw Error(o.where, "mesh '" + o.mesh_file + "' is " + std::to_string(size) +
                             " bytes, more than the limit of 2 GiB");
  std::ifstream in(o.mesh_file, std::ios::binary);
  char head[84] = {};
  in.read(head, sizeof head);
  const std::streamsize got = in.gcount();
  if (got >= 3 && std::string(head, 3) == "ply") {
    in.clear();
    in.seekg(0);
    std::string line;
    uintmax_t declared = 0;
    bool ended = false;
    for (int k = 0; k < 10000 && std::getline(in, line); ++k) {
      if (line.rfind("end_header", 0) == 0) {
        ended = true;
        break;
      }
      // Only the header's keywords: Assimp 5.2's PLY reader looped forever on a header line it
      // did not know ("propert", found by scripts/fuzz.sh mesh).
      std::istringstream ws(line);
      std::string first;
      ws >> first;
      if (first.empty() && k > 0) continue;  // a blank line
      if (k == 0 ? first != "ply"
                 : first != "format" && first != "comment" && first != "obj_info" &&
                       first != "element" && first != "property")
        throw Error(o.where,
                    "mesh '" + o.mesh_file + "': PLY header line " + std::to_string(k + 1) +
                        " is not a PLY header line (ply, format, comment, obj_info, element, "
                        "property, end_header)");
      std::istringstream ls(line);
      std::string word, name;
      uintmax_t count = 0;
      if (ls >> word >> name >> count && word == "element") {
        declared += count;
        if (declared > size)
          throw Error(o.where, "mesh '" + o.mesh_file + "' declares " + std::to_string(declared) +
                                   " PLY elements but has only " + std::to_string(size) +
                                   " bytes; truncated or corrupt");
      }
    }
    if (!ended)
      throw Error(o.where, "mesh '" + o.mesh_file + "': the PLY header has no end_header line");
  } else if (got == 84 && std::string(head, 5) != "solid" && IsStlFile(o.mesh_file)) {
    uint32_t triangles;
    std::memcpy(&triangles, head + 80, 4);  // binary STL: little-endian count after the header
    if (84 + uintmax_t(triangles) * 50 > size)
      throw Error(o.where, "mesh '" + o.mesh_file + "' declares " + std::to_string(triangles) +
                               " STL triangles but has only " + std::to_string(size) +
                               " bytes; truncated or corrupt");
  }
}

// The object's mesh in object-local micrometres: generated, or read with Assimp and scaled.
TriangleMesh LocalMesh(const ObjectSpec& o) {
  if (o.mesh) return *o.mesh;
  CheckMeshFileSizes(o);
  Assimp::Importer importer;
  // Read first, check every face's vertex indices, and only then post-process: Assimp's steps
  // (triangulation, joining vertices) index vertices without checking, and a corrupt file (a
  // binary PLY naming vertex 2^24) crashed inside them (found by scripts/fuzz.sh mesh).
  const aiScene* sc = nullptr;
  try {
    sc = importer.ReadFile(o.mesh_file, 0);
  } catch (const std::exception& e) {  // an Assimp assertion (above)
    throw Error(o.where, "cannot read mesh '" + o.mesh_file + "': " + e.what() + "; corrupt file");
  }
  if (!sc || !sc->mNumMeshes)
    throw Error(o.where, "cannot read mesh '" + o.mesh_file + "': " + importer.GetErrorString());
  for (unsigned k = 0; k < sc->mNumMeshes; ++k) {
    const aiMesh* mesh = sc->mMeshes[k];
    if (!mesh || (mesh->mNumVertices && !mesh->mVertices) || (mesh->mNumFaces && !mesh->mFaces))
      throw Error(o.where, "mesh '" + o.mesh_file +
                               "': a mesh without vertex or face data; truncated or corrupt");
    for (unsigned f = 0; f < mesh->mNumFaces; ++f) {
      const aiFace& face = mesh->mFaces[f];
      if (face.mNumIndices && !face.mIndices)
        throw Error(o.where, "mesh '" + o.mesh_file + "': face " + std::to_string(f + 1) +
                                 " has no indices");
      for (unsigned i = 0; i < face.mNumIndices; ++i)
        if (face.mIndices[i] >= mesh->mNumVertices)
          throw Error(o.where, "mesh '" + o.mesh_file + "': face " + std::to_string(f + 1) +
                                   " names vertex " + std::to_string(face.mIndices[i] + 1) +
                                   " of " + std::to_string(mesh->mNumVertices) +
                                   "; truncated or corrupt");
    }
  }
  try {
    sc = importer.ApplyPostProcessing(aiProcess_Triangulate | aiProcess_JoinIdenticalVertices |
                                      aiProcess_PreTransformVertices);
  } catch (const std::exception& e) {  // an Assimp assertion (above)
    throw Error(o.where, "cannot read mesh '" + o.mesh_file + "': " + e.what() + "; corrupt file");
  }
  if (!sc || !sc->mNumMeshes)
    throw Error(o.where, "cannot read mesh '" + o.mesh_file + "': " + importer.GetErrorString());
  TriangleMesh m;
  for (unsigned k = 0; k < sc->mNumMeshes; ++k) {
    const aiMesh* mesh = sc->mMeshes[k];
    const unsigned base = static_cast<unsigned>(m.vertices.size());
    for (unsigned v = 0; v < mesh->mNumVertices; ++v) {
      const aiVector3D& a = mesh->mVertices[v];
      const Vec3 p = Vec3(a.x, a.y, a.z) * o.mesh_scale_um;
      if (!IsFinite(p)) throw Error(o.where, "mesh '" + o.mesh_file + "' has NaN/Inf vertices");
      m.vertices.push_back(p);
    }
    for (unsigned f = 0; f < mesh->mNumFaces; ++f) {
      const aiFace& face = mesh->mFaces[f];
      for (unsigned k = 0; k < face.mNumIndices; ++k)
        if (face.mIndices[k] >= mesh->mNumVertices)
          throw Error(o.where, "mesh '" + o.mesh_file + "': face " + std::to_string(f + 1) +
                                   " names vertex " + std::to_string(face.mIndices[k] + 1) +
                                   " of " + std::to_string(mesh->mNumVertices) +
                                   "; truncated or corrupt");
      if (face.mNumIndices == 3)
        m.triangles.push_back(
            {base + face.mIndices[0], base + face.mIndices[1], base + face.mIndices[2]});
      else
        m.triangles.push_back({base, base, base});  // points/lines: counted as degenerate
    }
  }
  return m;
}

// A mesh file read, checked and oriented, in object-local micrometres. Fits build a scene per
// evaluation with the same mesh (only its pose or material changes), so the last few are kept,
// keyed by path, scale, size and modification time: a changed file is read again.
struct OrientedMesh {
  TriangleMesh mesh;
  MeshReport report;
};

std::shared_ptr<const OrientedMesh> Orient(TriangleMesh m) {
  auto out = std::make_shared<OrientedMesh>();
  out->report = CheckAndOrientMesh(&m);
  out->mesh = std::move(m);
  return out;
}

std::shared_ptr<const OrientedMesh> CachedLocalMesh(const ObjectSpec& o) {
  if (o.mesh) return Orient(*o.mesh);
  std::error_code ec;
  const auto size = std::filesystem::file_size(o.mesh_file, ec);
  const auto mtime = std::filesystem::last_write_time(o.mesh_file, ec);
  if (ec) return Orient(LocalMesh(o));  // LocalMesh reports the unreadable file
  char scale[32];
  std::snprintf(scale, sizeof scale, "%a", o.mesh_scale_um);
  const std::string key = o.mesh_file + "|" + scale + "|" + std::to_string(size) + "|" +
                          std::to_string(mtime.time_since_epoch().count());
  static std::mutex mu;
  static std::list<std::pair<std::string, std::shared_ptr<const OrientedMesh>>> cache;  // MRU first
  {
    std::lock_guard<std::mutex> lock(mu);
    for (auto it = cache.begin(); it != cache.end(); ++it)
      if (it->first == key) {
        cache.splice(cache.begin(), cache, it);
        return it->second;
      }
  }
  auto m = Orient(LocalMesh(o));
  std::lock_guard<std::mutex> lock(mu);
  cache.emplace_front(key, m);
  if (cache.size() > 4) cache.pop_back();
  return m;
}

void LoadMesh(const ObjectSpec& o, std::vector<float>* verts, std::vector<unsigned>* idx,
              MeshInfo* info) {
  const std::shared_ptr<const OrientedMesh> om = CachedLocalMesh(o);
  const TriangleMesh& m = om->mesh;
  const MeshReport& rep = om->report;
  const std::string what = o.mesh ? o.shape_description : "mesh '" + o.mesh_file + "'";
  if (rep.triangles == 0) throw Error(o.where, what + " has no usable triangles");
  if (!rep.ok())
    throw Error(o.where, what + " does not enclose a volume: " + rep.Summary() +
                             ". Refraction needs a closed surface; repair the mesh "
                             "(e.g. close holes, remove self-intersections)");
  const Mat3 rot = RotationFromEulerDeg(o.rotation_deg.x, o.rotation_deg.y, o.rotation_deg.z);
  for (const Vec3& v : m.vertices) {
    const Vec3 p = rot * v + o.center_um;
    // Embree holds vertices in float: a coordinate beyond its range would become Inf.
    if (!(std::abs(p.x) < 1e30 && std::abs(p.y) < 1e30 && std::abs(p.z) < 1e30))
      throw Error(o.where,
                  what + " has a vertex beyond 1e30 um after scaling and placing; check scale_um");
    verts->insert(verts->end(), {float(p.x), float(p.y), float(p.z)});
  }
  for (const auto& t : m.triangles) idx->insert(idx->end(), {t[0], t[1], t[2]});
  info->triangles = rep.triangles;
  info->signed_volume_um3 = rep.signed_volume_um3;
  info->flipped = rep.flipped;
  info->degenerate_removed = rep.degenerate_removed;
}

}  // namespace

Geometry::Geometry(const std::vector<ObjectSpec>& objects, double max_offset_us) {
  double min_z = 1e300;
  std::vector<Vec3> mesh_travel;  // per mesh: its displacement at the pulse's last offset
  for (size_t i = 0; i < objects.size(); ++i) {
    const ObjectSpec& o = objects[i];
    const int id = static_cast<int>(i);
    const double sweep = o.SweepUm(max_offset_us);
    double size = 0, lowest_z = 1e300;  // the object's lowest z (meshes: their lowest vertex)
    switch (o.shape) {
      case ShapeType::kSphere:
        spheres_.push_back({o.center_um, o.radius_um, o.radius_um * o.radius_um, id});
        size = o.radius_um;
        break;
      case ShapeType::kEllipsoid:
      case ShapeType::kBox: {
        FramedShape f;
        f.center = o.center_um;
        f.rot = RotationFromEulerDeg(o.rotation_deg.x, o.rotation_deg.y, o.rotation_deg.z);
        f.rot_t = f.rot.Transposed();
        f.half = o.semi_axes_um;
        f.inv_half = {1 / f.half.x, 1 / f.half.y, 1 / f.half.z};
        f.object = id;
        (o.shape == ShapeType::kBox ? boxes_ : ellipsoids_).push_back(f);
        size = Length(o.semi_axes_um);
        break;
      }
      case ShapeType::kMesh: {
        std::vector<float> v;
        std::vector<unsigned> idx;
        MeshInfo info;
        LoadMesh(o, &v, &idx, &info);
        double r2 = 0;
        for (size_t k = 0; k < v.size(); k += 3) {
          const Vec3 p(v[k], v[k + 1], v[k + 2]);
          r2 = std::max(r2, Dot(p - o.center_um, p - o.center_um));
          lowest_z = std::min(lowest_z, p.z);
        }
        size = std::sqrt(r2);
        vertices_.push_back(std::move(v));
        indices_.push_back(std::move(idx));
        mesh_object_.push_back(id);
        mesh_info_.push_back(info);
        mesh_travel.push_back(o.velocity_um_per_us * max_offset_us);
        break;
      }
    }
    eps_.push_back((o.shape == ShapeType::kMesh ? kMeshEpsilon : kAnalyticEpsilon) *
                   std::max(size, Length(o.center_um) * 1e-3 + size));
    // A moving object's bounds hold it wherever it is during the exposure (its sweep).
    extent_um_ = std::max(extent_um_, Length(o.center_um) + size + sweep);
    bound_center_.push_back(o.center_um);
    bound_radius_.push_back(size + sweep);
    if (o.shape != ShapeType::kMesh) lowest_z = o.center_um.z - size;
    min_z = std::min(min_z, lowest_z - sweep);
  }
  min_z_um_ = objects.empty() ? 0 : min_z;

  if (!vertices_.empty()) {
    RTCDevice dev = rtcNewDevice(nullptr);
    if (!dev) throw Error("Embree device could not be created");
    RTCScene scene = rtcNewScene(dev);
    rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_HIGH);
    // Watertight traversal: rays must not slip between triangles that share an edge.
    rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    for (size_t m = 0; m < vertices_.size(); ++m) {
      RTCGeometry g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
      const size_t nv = vertices_[m].size() / 3;
      const Vec3 travel = mesh_travel[m];
      if (Dot(travel, travel) > 0) {
        // A moving mesh: Embree's linear motion blur between its positions at the pulse's first
        // (-max) and last (+max) offsets; a ray at time (t + max) / (2 max) meets it where it
        // is at t (the interpolation is exact for uniform motion).
        rtcSetGeometryTimeStepCount(g, 2);
        for (unsigned step = 0; step < 2; ++step) {
          const Vec3 by = step == 0 ? -travel : travel;
          std::vector<float>& v = moving_vertices_.emplace_back(vertices_[m]);
          for (size_t k = 0; k < nv; ++k) {
            v[3 * k] = float(v[3 * k] + by.x);
            v[3 * k + 1] = float(v[3 * k + 1] + by.y);
            v[3 * k + 2] = float(v[3 * k + 2] + by.z);
          }
          rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, step, RTC_FORMAT_FLOAT3, v.data(),
                                     0, 3 * sizeof(float), nv);
        }
      } else {
        rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                   vertices_[m].data(), 0, 3 * sizeof(float), nv);
      }
      rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, indices_[m].data(),
                                 0, 3 * sizeof(unsigned), indices_[m].size() / 3);
      rtcCommitGeometry(g);
      rtcAttachGeometryByID(scene, g, static_cast<unsigned>(m));
      rtcReleaseGeometry(g);
    }
    rtcCommitScene(scene);
    device_ = dev;
    scene_ = scene;
  }
}

Geometry::~Geometry() {
  if (scene_) rtcReleaseScene(static_cast<RTCScene>(scene_));
  if (device_) rtcReleaseDevice(static_cast<RTCDevice>(device_));
}

bool Geometry::IntersectMesh(const Vec3& o, const Vec3& d, Hit* hit, float time) const {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  RTCRayHit rh;
  rh.ray.org_x = float(o.x), rh.ray.org_y = float(o.y), rh.ray.org_z = float(o.z);
  rh.ray.dir_x = float(d.x), rh.ray.dir_y = float(d.y), rh.ray.dir_z = float(d.z);
  rh.ray.tnear = 0.f;
  rh.ray.tfar = std::numeric_limits<float>::infinity();
  rh.ray.mask = 0xFFFFFFFFu;
  rh.ray.flags = 0;
  rh.ray.time = time;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(static_cast<RTCScene>(scene_), &ctx, &rh);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  // Normal from our own (outward-wound) triangle, in double, rather than Embree's Ng.
  const auto& v = vertices_[rh.hit.geomID];
  const auto& ix = indices_[rh.hit.geomID];
  auto V = [&](unsigned k) { return Vec3(v[3 * k], v[3 * k + 1], v[3 * k + 2]); };
  const Vec3 a = V(ix[3 * rh.hit.primID]), b = V(ix[3 * rh.hit.primID + 1]),
             c = V(ix[3 * rh.hit.primID + 2]);
  const Vec3 n = Cross(b - a, c - a);
  const double len = Length(n);
  if (!(len > 0)) return false;  // degenerate triangle: treat as no surface
  hit->t = rh.ray.tfar;
  hit->normal = n / len;
  hit->object = mesh_object_[rh.hit.geomID];
  return true;
}

}  // namespace raymatch::simulate
