#pragma once
// Monte Carlo non-sequential ray tracer: source -> objects -> corrector -> objective -> stop ->
// tube lens -> sensor. Each ray carries full weight; at an interface it reflects with the
// Fresnel probability R and is transmitted otherwise, so hits count like photons.
//
// The tracer is assembled from what the scene declares: the partial-reflection branch, the
// corrector stage and the Embree mesh query are compile-time switches of the inner loop, chosen
// once per image. Rays are independent Philox streams addressed by (seed, plane, ray index) and
// pixel counts are integers summed from per-thread buffers, so an image is bit-identical for any
// thread count.
#include <array>
#include <atomic>
#include <complex>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "raymatch/core/image.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::simulate {

/// What became of a ray. Every traced ray ends in exactly one fate.
enum class Fate : int {
  kDetected = 0,       ///< reached a sensor pixel
  kOutsideNa,          ///< blocked by the aperture stop, a lens rim or the corrector rim
  kMissedSensor,       ///< passed the optics but fell outside the sensor
  kAbsorbedCorrector,  ///< removed by a corrector ring's transmission draw
  kInteractionCap,     ///< more interface events than max_interactions
  kEscaped,            ///< left the objects travelling away from the objective (z' <= 0)
  kLostInside,         ///< no exit surface found from inside an object (numerical failure)
  kGrinStepCap,        ///< gradient-index integration exceeded grin max_steps in one segment
  kCount
};
const char* FateName(Fate f);
inline constexpr int kNumFates = static_cast<int>(Fate::kCount);
inline constexpr int kNumPathClasses = 8;

/// Work counters. An effect a scene does not declare leaves its counter at zero.
struct TraceCounters {
  std::array<uint64_t, kNumFates> fates{};
  uint64_t interface_events = 0;     ///< refractions + reflections at object surfaces
  uint64_t fresnel_evaluations = 0;  ///< partial-reflection branch decisions
  uint64_t corrector_tests = 0;      ///< rays tested against corrector rings
  uint64_t mesh_queries = 0;         ///< Embree BVH queries
  uint64_t shape_queries = 0;        ///< nearest-hit searches over analytic/mesh objects
  uint64_t rays_hitting_objects = 0;
  uint64_t grin_steps = 0;          ///< accepted gradient-index integration steps
  uint64_t grin_segments = 0;       ///< ray segments integrated through index fields
  uint64_t grin_uniform_steps = 0;  ///< straight steps across uniform grid cells
  uint64_t motion_draws = 0;        ///< emission times drawn (rays that can meet moving objects)
  uint64_t wavelength_draws = 0;    ///< wavelengths drawn (rays that can meet dispersive objects)
  /// Debye-style path classes of the first departure from the first object hit:
  /// [0] reflected externally, [k>=1] transmitted with k-1 internal reflections (7 = 6 or more).
  std::array<uint64_t, kNumPathClasses> path_class{};
  void Add(const TraceCounters& o);
  uint64_t total_fates() const;
};

struct PlaneResult {
  Image counts;  ///< hits per pixel (float32 holding integers)
  double defocus_um = 0;
  uint64_t rays = 0;
  TraceCounters counters;
  double seconds = 0;
  int threads = 0;    ///< worker threads per process
  int ranks = 1;      ///< MPI ranks that traced the image together (core/cluster.h)
  bool simd = false;  ///< the plane went through the SIMD packet path (Simulator::Effects
                      ///< says whether a scene can; RunControl::simd whether it may)
};

/// Which of a plane's rays Simulator::Trace traces. Every ray keeps the random stream TracePlane
/// gives it, so images of disjoint selections add up to the image of their union (fits trace
/// once the rays that cannot meet an object and re-trace only the others).
struct RaySelection {
  uint64_t first = 0;              ///< the rays [first, first + count) ...
  uint64_t count = 0;              ///<
  const uint64_t* list = nullptr;  ///< ... or these `count` ray indices instead
  const uint64_t* skip = nullptr;  ///< ascending indices left out of the range (others ignored)
  size_t skip_count = 0;
  /// Leave out the rays whose straight line from the source (before any object) passes within
  /// sqrt(split_r2) of split_center, and report their indices (Trace's `near`).
  bool split = false;
  Vec3 split_center;
  double split_r2 = 0;

  /// The rays [first, last).
  static RaySelection Range(uint64_t first, uint64_t last) {
    RaySelection s;
    s.first = first, s.count = last - first;
    return s;
  }
  /// The listed rays, in the list's order.
  static RaySelection Of(std::span<const uint64_t> rays) {
    RaySelection s;
    s.list = rays.data(), s.count = rays.size();
    return s;
  }
  /// This range without the listed rays (ascending; entries outside the range are ignored).
  RaySelection Except(std::span<const uint64_t> excluded) const {
    RaySelection s = *this;
    s.skip = excluded.data(), s.skip_count = excluded.size();
    return s;
  }
  /// This range (with or without Except; not a list) without the rays whose line passes within
  /// radius_um of center_um: Trace reports them.
  RaySelection SplitBy(const Vec3& center_um, double radius_um) const {
    RaySelection s = *this;
    s.split = true, s.split_center = center_um, s.split_r2 = radius_um * radius_um;
    return s;
  }
};

/// The SIMD instruction set the packet path uses on this CPU (chosen at run time), e.g. "AVX3"
/// (AVX-512), "AVX2", "SSE4" (Google Highway's target names).
const char* SimdTarget();

/// Controls that do not change the physics.
struct RunControl {
  int threads = 0;        ///< 0: scene's value, then all cores
  bool progress = false;  ///< progress bar on stderr
  std::string label;      ///< shown in the progress bar
  /// Trace in SIMD packets where the scene allows (the same image bit for bit); false: one ray
  /// at a time, for comparisons.
  bool simd = true;
};

class WaterMapTable;  // water.h

class Simulator {
 public:
  /// Builds geometry (Embree only for meshes), sources and optics. Throws Error on bad input.
  explicit Simulator(const Scene& scene);
  ~Simulator();

  /// Traces the selected rays of the plane with the objective focused at `defocus_um`;
  /// `plane_index` selects the random streams (different planes get independent noise, like
  /// separate exposures). A split selection appends the rays it leaves out to `near`
  /// (ascending; required then). Counters cover the traced rays only. The entry points below
  /// are this call with the selections they name.
  PlaneResult Trace(double defocus_um, uint32_t plane_index, const RaySelection& rays,
                    const RunControl& control = {}, std::vector<uint64_t>* near = nullptr) const;

  /// The rays [0, rays) of the plane.
  PlaneResult TracePlane(double defocus_um, uint32_t plane_index, uint64_t rays,
                         const RunControl& control = {}) const;

  /// Traces only the listed rays of the plane, each with the stream TracePlane gives it, so
  /// images of disjoint lists add up to the image of their union (fits trace once the rays
  /// that cannot meet an object and re-trace only the others). Counters cover listed rays only.
  PlaneResult TraceRays(double defocus_um, uint32_t plane_index,
                        std::span<const uint64_t> ray_indices,
                        const RunControl& control = {}) const;

  /// Traces the rays [0, rays) of the plane except the listed ones (ascending indices): with
  /// TraceRays on the same list, the two images add up to TracePlane's.
  PlaneResult TracePlaneExcept(double defocus_um, uint32_t plane_index, uint64_t rays,
                               const std::vector<uint64_t>& excluded,
                               const RunControl& control = {}) const;

  /// The rays [first, last) of the plane except the listed ones (ascending; entries outside the
  /// range are ignored). Images of consecutive ranges add up to the image of their union.
  PlaneResult TraceRangeExcept(double defocus_um, uint32_t plane_index, uint64_t first,
                               uint64_t last, std::span<const uint64_t> excluded,
                               const RunControl& control = {}) const;

  /// SplitRaysBySphere and TraceRangeExcept in one sampling pass: traces the rays [first, last)
  /// whose straight line misses the sphere and appends the others' indices (ascending) to
  /// `near`. With TraceRays on those indices the two images add up to the range's image.
  PlaneResult TraceFarRays(double defocus_um, uint32_t plane_index, uint64_t first, uint64_t last,
                           const Vec3& center_um, double radius_um, std::vector<uint64_t>* near,
                           const RunControl& control = {}) const;

  /// Splits the rays [0, rays) of a plane by whether the straight line of each (as the source
  /// emits it, before any object) passes within `radius_um` of `center_um`. Either output may
  /// be null; indices come out ascending. Rays the source rejects go to `far`.
  void SplitRaysBySphere(uint32_t plane_index, uint64_t rays, const Vec3& center_um,
                         double radius_um, std::vector<uint64_t>* near,
                         std::vector<uint64_t>* far) const {
    SplitRaysBySphere(plane_index, 0, rays, center_um, radius_um, near, far);
  }
  /// The same for the rays [first, last); indices are appended.
  void SplitRaysBySphere(uint32_t plane_index, uint64_t first, uint64_t last, const Vec3& center_um,
                         double radius_um, std::vector<uint64_t>* near,
                         std::vector<uint64_t>* far) const;

  /// Rays per image that give `photons_per_pixel` mean hits in the flat field, from a fixed-seed
  /// pilot run without objects (the experimenter's flat-field signal x well capacity).
  uint64_t RaysForPhotonTarget(double photons_per_pixel,
                               double* hits_per_pixel_per_ray = nullptr) const;

  /// One ray through the objects only (no source, no optics), with the scene's physics and the
  /// random stream of `ray_index`: where and in which direction it leaves the last surface,
  /// and its optical path there. For tests, accuracy studies and physical optics.
  struct ObjectExit {
    Vec3 origin, direction;
    /// The optical path from the origin given to `origin` (um): the integral of n ds through
    /// the medium, homogeneous objects and gradient-index fields (0 for a ray that meets no
    /// object). Meaningless when `ended`.
    double optical_path_um = 0;
    bool ended = false;  ///< ended inside (then `fate` says why)
    Fate fate = Fate::kDetected;
    TraceCounters counters;
  };
  ObjectExit TraceThroughObjects(const Vec3& origin, const Vec3& direction,
                                 uint64_t ray_index = 0) const;

  /// Physical optics: one ray of a coherent wave through the objects along a chosen branch of
  /// the surfaces' Fresnel splits, carrying its complex field. At its k-th surface event (k from
  /// 0) the ray reflects if bit k of `reflect_mask` is set and is refracted otherwise; total
  /// internal reflection always reflects (a transmission asked for there sets `evanescent`).
  /// `field` (the complex field vector, perpendicular to `direction`) is split into its s and p
  /// parts at each surface and multiplied by the power-normalised amplitude coefficients
  /// (ComplexFresnel's r, and t x sqrt(n2 cos t / n1 cos i)), so |field|^2 is the ray tube's
  /// power share and the tube's area change is left to the caller. A ray with more than
  /// `max_events` surface events ends (fate kInteractionCap). The path is recorded as straight
  /// or curved segments with the optical path at each start (the integral of n ds from
  /// `origin`).
  struct FieldRay {
    struct Segment {
      Vec3 point, direction;       ///< where the segment starts and its direction there
      double optical_path_um = 0;  ///< from the origin to `point`
      double index = 1;            ///< the medium's index along it (at its start)
      bool curved = false;         ///< in a gradient-index object
      Vec3 normal;                 ///< the surface's normal at `point` (either way; [0]: none)
    };
    static constexpr int kMaxEvents = 8;
    std::array<Segment, kMaxEvents + 1> segments{};  ///< [0]: from the origin
    int n_segments = 0;
    int events = 0;                               ///< surface events met
    std::array<std::complex<double>, 3> field{};  ///< leaving the last surface
    Vec3 origin, direction;                       ///< where and how it leaves the objects
    double optical_path_um = 0;                   ///< from the origin given to `origin`
    bool ended = false;                           ///< ended inside (`fate` says why)
    bool evanescent = false;  ///< a transmission was asked for beyond the critical angle
    Fate fate = Fate::kDetected;
  };
  FieldRay TraceFieldRay(const Vec3& origin, const Vec3& direction,
                         const std::array<std::complex<double>, 3>& field, uint32_t reflect_mask,
                         int max_events) const;

  /// Rays per image for this scene (given directly, or from the photon target).
  uint64_t RaysPerImage() const;

  /// The stages this tracer runs, e.g. {"source:cone", "refraction", "partial_reflection:..."},
  /// and last whether the SIMD packet path takes the scene: "simd_packets", or
  /// "scalar_only:<reason>" (point_source, ray_list_source, spatial_map, ...).
  std::vector<std::string> Effects() const;
  const Scene& scene() const { return scene_; }
  double source_plane_z_um() const;
  double object_pixel_um() const;  ///< pixel pitch referred to the object plane
  /// Object `object`'s water density field at other wavelengths, as rays of a spectral scene see
  /// it (WaterMapTable); null for other objects and monochromatic scenes.
  const WaterMapTable* WaterMapOf(int object) const;
  double field_radius_um() const;  ///< the source field radius in use (given or automatic)
  /// A light field's radiance integrated over direction cosines (map units; 0 for other
  /// sources): a continued light field's parts inside and beyond the NA (SourceSpec::edge_part)
  /// need rays in the ratio of their weights.
  double source_weight() const;
  /// A bounding sphere (centre, radius; micrometres) of each object, in scene order.
  std::vector<std::pair<Vec3, double>> ObjectBounds() const;
  /// One sphere that holds them all: centred on their bounding box, the least radius about that
  /// centre (none: the origin and 0).
  static std::pair<Vec3, double> EnclosingSphere(
      const std::vector<std::pair<Vec3, double>>& spheres);
  bool has_mesh_bvh() const;  ///< an Embree BVH was built

  struct Impl;  ///< defined in simulate/src/tracer_impl.h only

 private:
  Scene scene_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace raymatch::simulate
