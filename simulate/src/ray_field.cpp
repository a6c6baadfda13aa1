// Physical optics from rays (ray_field.h): the silhouette's shadow and the branches' ray tubes
// sampled on the exit plane, Fourier transformed.
#include "raymatch/simulate/ray_field.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <unordered_map>

#include "raymatch/core/error.h"

namespace raymatch::simulate {
namespace {

using C = std::complex<double>;
constexpr double kInf = std::numeric_limits<double>::infinity();

/// The lattice of ray starts on the plane z_start: point (I, J) at (x_lo + I h, y_lo + J h),
/// h the finest spacing; coarse points are every `step` (2^levels) of them.
struct Lattice {
  double x_lo = 0, y_lo = 0, z_start = 0, h = 0;
  int64_t step = 1, ni = 0, nj = 0;  // coarse cells along x and y
  Vec3 Start(int64_t i, int64_t j) const {
    return {x_lo + double(i) * h, y_lo + double(j) * h, z_start};
  }
  uint64_t Key(int64_t i, int64_t j) const {
    return uint64_t(i) * uint64_t(nj * step + 1) + uint64_t(j);
  }
};

struct Wave {
  const Simulator* sim = nullptr;
  Vec3 din, origin;
  CVec3 e0{};
  double k = 0, k0 = 0;  // wavenumbers in the medium and in vacuum (rad / um)
  double n_medium = 1;
  double plane_z = 0;              // the exit plane, where the branches' field is sampled
  double k_pass = 0, k_taper = 0;  // a ray's field tapers off from k_pass to k_pass + k_taper
  double Taper(double kt) const {
    if (kt <= k_pass) return 1;
    if (kt >= k_pass + k_taper) return 0;
    return 0.5 * (1 + std::cos(M_PI * (kt - k_pass) / k_taper));
  }
};

/// A straight segment of a ray as positions p = b + w tau over its optical path tau.
struct Line {
  Vec3 b, w;
  double lo = 0, hi = kInf;
  bool curved = false;
  Vec3 normal;  // the surface's where it begins (either way; the first line: none)
};

/// One traced ray of a branch.
struct Node {
  bool valid = false;    // exits after exactly the branch's events, forward
  bool goes_on = false;  // meets more surfaces than the branch's
  double kx = 0, ky = 0;
  double px = 0, py = 0;  // where the ray (extended) crosses the origin's z-plane
  double phi = 0;         // the wave's phase there
  double cos = 1;         // d.z
  double tau_plane = 0;   // the optical path there
  CVec3 e{};              // times the taper beyond the passed disc
  double power = 0;       // |E|^2 before the taper
  int n_lines = 0;
  std::array<Line, Simulator::FieldRay::kMaxEvents + 1> lines;
};

Node TraceNode(const Wave& w, const Lattice& lat, int64_t i, int64_t j, uint32_t mask, int events) {
  Node nd;
  const Vec3 s = lat.Start(i, j);
  const Simulator::FieldRay r = w.sim->TraceFieldRay(s, w.din, w.e0, mask, events);
  nd.goes_on = r.ended && r.fate == Fate::kInteractionCap;
  nd.valid = !r.ended && !r.evanescent && r.events == events && r.direction.z > 0;
  if (!nd.valid) return nd;
  const Vec3 d = r.direction, rel = r.origin - w.origin;
  nd.kx = w.k * d.x, nd.ky = w.k * d.y;
  const double to_plane = (w.plane_z - r.origin.z) / d.z;  // along the ray (may be negative)
  nd.px = rel.x + d.x * to_plane, nd.py = rel.y + d.y * to_plane;
  nd.cos = d.z;
  nd.tau_plane = r.optical_path_um + w.n_medium * to_plane;
  nd.phi = w.k * Dot(w.din, s - w.origin) + w.k0 * nd.tau_plane;
  const double taper = w.Taper(std::hypot(nd.kx, nd.ky));
  for (int c = 0; c < 3; ++c) nd.e[c] = r.field[c] * taper, nd.power += std::norm(r.field[c]);
  nd.n_lines = r.n_segments;
  for (int q = 0; q < r.n_segments; ++q) {
    const Simulator::FieldRay::Segment& g = r.segments[q];
    Line& l = nd.lines[q];
    l.w = g.direction / g.index;
    l.b = g.point - l.w * g.optical_path_um;
    l.lo = g.optical_path_um;
    l.hi = q + 1 < r.n_segments ? r.segments[q + 1].optical_path_um : kInf;
    l.curved = g.curved;
    l.normal = g.normal;
  }
  return nd;
}

/// A ray tube's cross-section: the sides p1 - p0 and p2 - p0 of its triangle in a basis (e1, e2)
/// across the mean direction u of its rays, as the matrix [d1.e1 d2.e1; d1.e2 d2.e2].
struct TubeSection {
  Vec3 e1, e2;
  explicit TubeSection(const Vec3& u)
      : e1(Normalize(Cross(u, std::abs(u.x) < 0.6 ? Vec3(1, 0, 0) : Vec3(0, 1, 0)))),
        e2(Cross(u, e1)) {}
  void Of(const Vec3& d1, const Vec3& d2, double m[4]) const {
    m[0] = Dot(d1, e1), m[1] = Dot(d2, e1), m[2] = Dot(d1, e2), m[3] = Dot(d2, e2);
  }
};

/// The focal lines a tube passes from cross-section s0 to s1 (TubeSection), whose areas have the
/// signs o0 and o1 (+-1): the linear map L taking the first to the second is mirrored (det L <
/// 0) past one focal line and turned about (trace L < 0) past two, as through a point focus,
/// where the section's area only touches zero (Kravtsov and Orlov, Caustics, Catastrophes and
/// Wave Fields, sec. 2.3: the Maslov index of a ray tube).
int FocalLinesBetween(const double s0[4], const double s1[4], int o0, int o1) {
  if (o0 != o1) return 1;
  // trace(S1 S0^-1) with S0^-1 = adj(S0) / det0: its sign, with det0's sign o0.
  const double tr = (s1[0] * s0[3] - s1[1] * s0[2] - s1[2] * s0[1] + s1[3] * s0[0]) * o0;
  return tr < 0 ? 2 : 0;
}

int SignOf(double v) { return v < 0 ? -1 : 1; }

/// The sign of the area of triangle p on the surface where the three lines `l` begin, seen
/// along u: (A . N)(N . u), N the surface's mean normal there (each ray's turned to the first's
/// side), A the triangle's area vector.
int SurfaceOrientation(const Vec3 p[3], const Line* const l[3], const Vec3& u) {
  Vec3 sum = l[0]->normal;
  for (int r = 1; r < 3; ++r)
    sum = sum + (Dot(l[r]->normal, sum) < 0 ? l[r]->normal * -1.0 : l[r]->normal);
  const Vec3 nn = Normalize(sum);
  return SignOf(Dot(Cross(p[1] - p[0], p[2] - p[0]), nn) * Dot(nn, u));
}

/// The focal lines the tube of three rays passes from the start to the exit plane, on every
/// straight segment (curved ones are skipped) from the triangle of its rays' points where the
/// segment begins (on the start plane or a surface) to the triangle where it ends (on the next
/// surface, or for the last segment on the exit plane; counted negative where the plane lies
/// before the exits on average). A triangle on a surface is oriented, for the segments on both
/// sides, by its area along the surface normal (A.N)(N.u), so they agree where it degenerates:
/// where a caustic touches a surface the two counts change together and their sum stays; on the
/// exit plane the count changes where the triangle's area, and with it its share of the field,
/// passes zero. The field stays continuous as caustics move with the objects.
int FocalLines(const Node& a, const Node& b, const Node& c) {
  int count = 0;
  const int n = std::min({a.n_lines, b.n_lines, c.n_lines});
  const Node* nodes[3] = {&a, &b, &c};
  for (int q = 0; q < n; ++q) {
    const Line* l[3] = {&a.lines[q], &b.lines[q], &c.lines[q]};
    if (l[0]->curved || l[1]->curved || l[2]->curved) continue;
    const bool last = q + 1 == n;
    Vec3 p0[3], p1[3];
    double ahead = 0;  // the plane's mean optical path beyond the exits (last segment)
    for (int r = 0; r < 3; ++r) {
      const double end = last ? nodes[r]->tau_plane : l[r]->hi;
      p0[r] = l[r]->b + l[r]->w * l[r]->lo, p1[r] = l[r]->b + l[r]->w * end;
      ahead += end - l[r]->lo;
    }
    const Vec3 u = Normalize(l[0]->w + l[1]->w + l[2]->w);
    const TubeSection sec(u);
    double s0[4], s1[4];
    sec.Of(p0[1] - p0[0], p0[2] - p0[0], s0);
    sec.Of(p1[1] - p1[0], p1[2] - p1[0], s1);
    const int o0 = q > 0 ? SurfaceOrientation(p0, l, u) : SignOf(s0[0] * s0[3] - s0[1] * s0[2]);
    int o1 = SignOf(s1[0] * s1[3] - s1[1] * s1[2]);
    if (!last) {
      const Line* next[3] = {&a.lines[q + 1], &b.lines[q + 1], &c.lines[q + 1]};
      o1 = SurfaceOrientation(p1, next, u);
    }
    count +=
        last && ahead < 0 ? -FocalLinesBetween(s1, s0, o1, o0) : FocalLinesBetween(s0, s1, o0, o1);
  }
  return count;
}

/// A lattice triangle of a branch, ready to be rasterised on the plane.
struct Tri {
  uint64_t id[3];
  double px[3], py[3], kx[3], ky[3], phi[3], cos[3];
  CVec3 e[3];
  double area_in = 0, area_p = 0;  // on the incident wave and on the plane
  // sqrt(dA_in / dA_plane) at each ray, over the triangles that share it: the tube's amplitude
  // change (over sqrt(cos)).
  double gv[3] = {0, 0, 0};
  double focal_phase = 0;
};

/// The origin's z-plane sampled for the branches' field: nodes x = x_lo + p h, y = y_lo + q h,
/// n x n, periodic (the spectrum's grid step is 2 pi / (n h)).
struct PlaneGrid {
  int n = 0;
  double h = 0, x_lo = 0, y_lo = 0;
  double cell = 0;  // the refinement's length scale (the passed band's sampling step)
};

struct Branch {
  uint32_t mask = 0;
  int events = 0;
};

/// Traces and refines one branch's lattice cells and collects its triangles (in a fixed order).
class BranchMapper {
 public:
  /// With `replay`, the edges halved are those it lists (sorted lattice keys of their
  /// midpoints) instead of the refinement's tests; with `record`, the edges the tests halve are
  /// listed there (sorted).
  BranchMapper(const Wave& w, const Lattice& lat, const SpectrumGrid& g, const PlaneGrid& plane,
               const RaySpectrumSettings& set, Branch br, const std::vector<uint64_t>* replay,
               std::vector<uint64_t>* record)
      : w_(w),
        lat_(lat),
        g_(g),
        plane_(plane),
        set_(set),
        br_(br),
        replay_(replay),
        record_(record) {}

  /// The coarse lattice's nodes, then every coarse cell; false when no ray takes the branch.
  bool Run(std::vector<Tri>* tris, bool* goes_on, uint64_t* rays, double* power) {
    const int64_t nx = lat_.ni + 1, ny = lat_.nj + 1;
    coarse_.assign(size_t(nx * ny), Node{});
    tbb::parallel_for(int64_t(0), ny, [&](int64_t j) {
      for (int64_t i = 0; i < nx; ++i)
        coarse_[size_t(j * nx + i)] =
            TraceNode(w_, lat_, i * lat_.step, j * lat_.step, br_.mask, br_.events);
    });
    bool any = false, more = false;
    for (const Node& n : coarse_) any |= n.valid, more |= n.goes_on;
    *goes_on = more;
    *rays += uint64_t(nx * ny);
    if (!any) return false;
    std::vector<std::vector<Tri>> rows(size_t(lat_.nj));
    std::vector<uint64_t> row_rays(size_t(lat_.nj), 0);
    std::vector<double> row_power(size_t(lat_.nj), 0.0);
    std::vector<std::vector<uint64_t>> row_halved(size_t(lat_.nj));
    tbb::parallel_for(int64_t(0), lat_.nj, [&](int64_t cj) {
      Cells cells{this, {}, &rows[size_t(cj)], 0, 0, &row_halved[size_t(cj)]};
      for (int64_t ci = 0; ci < lat_.ni; ++ci) {
        const Node* c[4] = {&At(ci, cj), &At(ci + 1, cj), &At(ci + 1, cj + 1), &At(ci, cj + 1)};
        cells.Refine(ci * lat_.step, cj * lat_.step, lat_.step, c);
        cells.cache.clear();
      }
      row_rays[size_t(cj)] = cells.rays;
      row_power[size_t(cj)] = cells.power;
    });
    for (int64_t cj = 0; cj < lat_.nj; ++cj) {
      tris->insert(tris->end(), rows[size_t(cj)].begin(), rows[size_t(cj)].end());
      *rays += row_rays[size_t(cj)];
      *power += row_power[size_t(cj)];
      if (record_)
        record_->insert(record_->end(), row_halved[size_t(cj)].begin(),
                        row_halved[size_t(cj)].end());
    }
    if (record_) {
      std::sort(record_->begin(), record_->end());
      record_->erase(std::unique(record_->begin(), record_->end()), record_->end());
    }
    return true;
  }

 private:
  /// A lattice cell of side s (finest units) across the incident wave.
  double CellArea(int64_t s) const { return double(s * s) * lat_.h * lat_.h * std::abs(w_.din.z); }

  /// Whether directions within [kx_lo, kx_hi] x [ky_lo, ky_hi], grown by their own spread and
  /// one spectrum step, all lie beyond the taper.
  bool BeyondTaper(double kx_lo, double kx_hi, double ky_lo, double ky_hi) const {
    const double grow = std::max(kx_hi - kx_lo, ky_hi - ky_lo) + g_.dk;
    const double ex = std::max({kx_lo - grow, 0.0, -(kx_hi + grow)});
    const double ey = std::max({ky_lo - grow, 0.0, -(ky_hi + grow)});
    const double k_end = w_.k_pass + w_.k_taper;
    return ex * ex + ey * ey > k_end * k_end;
  }

  const Node& At(int64_t ci, int64_t cj) const { return coarse_[size_t(cj * (lat_.ni + 1) + ci)]; }

  /// One row of coarse cells (one thread): refined nodes cached by lattice key.
  struct Cells {
    const BranchMapper* m;
    std::unordered_map<uint64_t, Node> cache;
    std::vector<Tri>* out;
    uint64_t rays;
    double power;
    std::vector<uint64_t>* halved;  // the edges this row's tests halved (recording)

    const Node& Get(int64_t i, int64_t j) {
      const uint64_t key = m->lat_.Key(i, j);
      auto it = cache.find(key);
      if (it != cache.end()) return it->second;
      ++rays;
      return cache.emplace(key, TraceNode(m->w_, m->lat_, i, j, m->br_.mask, m->br_.events))
          .first->second;
    }

    /// A lattice point and its ray.
    struct Point {
      int64_t i, j;
      const Node* n;
    };

    /// Whether lattice point (i, j) lies on the lattice (outside it no ray meets an object).
    bool OnLattice(int64_t i, int64_t j) const {
      return i >= 0 && j >= 0 && i <= m->lat_.ni * m->lat_.step && j <= m->lat_.nj * m->lat_.step;
    }
    bool ValidAt(int64_t i, int64_t j) { return OnLattice(i, j) && Get(i, j).valid; }

    /// Whether the edge a -> b of length s is halved. A function of the edge alone (its rays and
    /// the two cells of side s on either side of it), so the two cells that share it agree and
    /// the triangles meet without cracks: halved where its rays differ in validity, where a
    /// cell beside it has rays of both kinds (the branch's edge is resolved to the finest
    /// level), or where its rays' crossings of the plane lie more than max_cell_steps band
    /// steps apart (unless both directions lie beyond the taper). Replaying a layout, as it
    /// was decided when the layout was recorded.
    bool Splits(const Point& a, const Point& b, int64_t s) {
      if (s < 2) return false;
      const uint64_t mid = m->lat_.Key((a.i + b.i) / 2, (a.j + b.j) / 2);
      if (m->replay_) return std::binary_search(m->replay_->begin(), m->replay_->end(), mid);
      const bool split = Tests(a, b);
      if (split && m->record_) halved->push_back(mid);
      return split;
    }

    /// The refinement's tests of Splits.
    bool Tests(const Point& a, const Point& b) {
      if (a.n->valid != b.n->valid) return true;
      if (a.n->valid) {
        const double extent = std::max(std::abs(a.n->px - b.n->px), std::abs(a.n->py - b.n->py));
        if (extent > m->set_.max_cell_steps * m->plane_.cell &&
            !m->BeyondTaper(std::min(a.n->kx, b.n->kx), std::max(a.n->kx, b.n->kx),
                            std::min(a.n->ky, b.n->ky), std::max(a.n->ky, b.n->ky)))
          return true;
      }
      // The cells on either side: the edge's perpendicular (-dj, di) and (dj, -di).
      const int64_t di = (b.i - a.i), dj = (b.j - a.j);
      for (int side : {1, -1}) {
        const int64_t oi = -dj * side, oj = di * side;
        if (ValidAt(a.i + oi, a.j + oj) != a.n->valid || ValidAt(b.i + oi, b.j + oj) != a.n->valid)
          return true;
      }
      return false;
    }

    /// The points the edge a -> b of length s is halved into (recursively), in order, ends
    /// excluded.
    void EdgePoints(const Point& a, const Point& b, int64_t s, std::vector<Point>* out) {
      if (!Splits(a, b, s)) return;
      const int64_t mi = (a.i + b.i) / 2, mj = (a.j + b.j) / 2;
      const Point mid{mi, mj, &Get(mi, mj)};
      EdgePoints(a, mid, s / 2, out);
      out->push_back(mid);
      EdgePoints(mid, b, s / 2, out);
    }

    /// Cell (i, j) of side s (finest units), corners c: 00, 10, 11, 01. Quartered where all four
    /// edges are halved; where only some are, a fan of triangles from its centre takes in the
    /// points its edges are halved into (the neighbours' corners), so no crack opens between
    /// cells of different sizes.
    void Refine(int64_t i, int64_t j, int64_t s, const Node* const c[4]) {
      int valid = 0;
      double kx_lo = kInf, kx_hi = -kInf, ky_lo = kInf, ky_hi = -kInf;
      for (int q = 0; q < 4; ++q) {
        if (!c[q]->valid) continue;
        ++valid;
        kx_lo = std::min(kx_lo, c[q]->kx), kx_hi = std::max(kx_hi, c[q]->kx);
        ky_lo = std::min(ky_lo, c[q]->ky), ky_hi = std::max(ky_hi, c[q]->ky);
      }
      if (valid == 0) return;
      if (valid == 4 && m->BeyondTaper(kx_lo, kx_hi, ky_lo, ky_hi)) {
        // Its power still counts (the branches' power is the light leaving forward); cells
        // across the branch's edge are refined on, for it.
        double e2 = 0;
        for (int q = 0; q < 4; ++q) e2 += c[q]->power / 4;
        power += e2 * m->CellArea(s);
        return;
      }
      const Point corner[4] = {
          {i, j, c[0]}, {i + s, j, c[1]}, {i + s, j + s, c[2]}, {i, j + s, c[3]}};
      bool split[4], all = true, any = false;
      for (int q = 0; q < 4; ++q) {
        split[q] = Splits(corner[q], corner[(q + 1) % 4], s);
        all &= split[q], any |= split[q];
      }
      if (!any) {
        Emit(corner, m->CellArea(s));
        return;
      }
      const int64_t h = s / 2;
      if (!all) {
        std::vector<Point> ring;
        for (int q = 0; q < 4; ++q) {
          ring.push_back(corner[q]);
          if (split[q]) EdgePoints(corner[q], corner[(q + 1) % 4], s, &ring);
        }
        Fan({i + h, j + h, &Get(i + h, j + h)}, ring);
        return;
      }
      const Node* mid[5] = {&Get(i + h, j), &Get(i + s, j + h), &Get(i + h, j + s), &Get(i, j + h),
                            &Get(i + h, j + h)};
      // (References into the cache stay valid: unordered_map does not move its nodes.)
      const Node* q00[4] = {c[0], mid[0], mid[4], mid[3]};
      const Node* q10[4] = {mid[0], c[1], mid[1], mid[4]};
      const Node* q11[4] = {mid[4], mid[1], c[2], mid[2]};
      const Node* q01[4] = {mid[3], mid[4], mid[2], c[3]};
      Refine(i, j, h, q00);
      Refine(i + h, j, h, q10);
      Refine(i + h, j + h, h, q11);
      Refine(i, j + h, h, q01);
    }

    /// The triangle of rays v (counter-clockwise on the lattice) over `area_in` of the incident
    /// wave: its power, and its tube unless its rays carry no field.
    void Triangle(const Point* const v[3], double area_in) {
      for (int q = 0; q < 3; ++q)
        if (!v[q]->n->valid) return;
      const Node &a = *v[0]->n, &b = *v[1]->n, &d = *v[2]->n;
      power += (a.power + b.power + d.power) / 3 * area_in;
      bool lit = false;  // (rays beyond the taper carry no field)
      for (int q = 0; q < 3; ++q)
        for (const C& e : v[q]->n->e) lit |= e != C(0);
      const double area_p =
          0.5 * std::abs((b.px - a.px) * (d.py - a.py) - (b.py - a.py) * (d.px - a.px));
      if (!lit || !(area_p > 0) || !(area_in > 0)) return;
      Tri tr;
      for (int q = 0; q < 3; ++q) {
        const Node& x = *v[q]->n;
        tr.id[q] = m->lat_.Key(v[q]->i, v[q]->j);
        tr.kx[q] = x.kx, tr.ky[q] = x.ky, tr.px[q] = x.px, tr.py[q] = x.py;
        tr.phi[q] = x.phi, tr.cos[q] = x.cos, tr.e[q] = x.e;
      }
      tr.area_in = area_in, tr.area_p = area_p;
      tr.focal_phase = -0.5 * M_PI * FocalLines(a, b, d);
      out->push_back(tr);
    }

    /// The lattice area of triangle (a, b, d) on the incident wave.
    double AreaIn(const Point& a, const Point& b, const Point& d) const {
      const double cross = double((b.i - a.i) * (d.j - a.j) - (b.j - a.j) * (d.i - a.i));
      return 0.5 * std::abs(cross) * m->lat_.h * m->lat_.h * std::abs(m->w_.din.z);
    }

    /// The two triangles of the cell with corners p (00, 10, 11, 01) and area `cell_area`,
    /// split along its 00-11 diagonal.
    void Emit(const Point p[4], double cell_area) {
      static constexpr int kTri[2][3] = {{0, 1, 2}, {0, 2, 3}};
      for (const auto& t : kTri) {
        const Point* v[3] = {&p[t[0]], &p[t[1]], &p[t[2]]};
        Triangle(v, 0.5 * cell_area);
      }
    }

    /// Triangles from `centre` to each side of the closed ring (counter-clockwise); where the
    /// centre's ray does not take the branch, from the ring's first ray that does.
    void Fan(const Point& centre, const std::vector<Point>& ring) {
      const size_t n = ring.size();
      if (centre.n->valid) {
        for (size_t k = 0; k < n; ++k) {
          const Point* v[3] = {&centre, &ring[k], &ring[(k + 1) % n]};
          Triangle(v, AreaIn(centre, ring[k], ring[(k + 1) % n]));
        }
        return;
      }
      size_t f = 0;
      while (f < n && !ring[f].n->valid) ++f;
      if (f == n) return;
      for (size_t k = 1; k + 1 < n; ++k) {
        const Point &b = ring[(f + k) % n], &d = ring[(f + k + 1) % n];
        const Point* v[3] = {&ring[f], &b, &d};
        Triangle(v, AreaIn(ring[f], b, d));
      }
    }
  };

  const Wave& w_;
  const Lattice& lat_;
  const SpectrumGrid& g_;
  const PlaneGrid& plane_;
  const RaySpectrumSettings& set_;
  Branch br_;
  const std::vector<uint64_t>* replay_;
  std::vector<uint64_t>* record_;
  std::vector<Node> coarse_;
};

/// The plane's rows a triangle's nodes cover (their cells, a node step wide, meet it),
/// [*jl, *jh] before they wrap (empty: jl > jh).
void RowsOf(const Tri& t, const PlaneGrid& pg, int* jl, int* jh) {
  const double y_lo = std::min({t.py[0], t.py[1], t.py[2]}) - 0.5 * pg.h;
  const double y_hi = std::max({t.py[0], t.py[1], t.py[2]}) + 0.5 * pg.h;
  *jl = int(std::ceil((y_lo - pg.y_lo) / pg.h));
  *jh = int(std::floor((y_hi - pg.y_lo) / pg.h));
}

/// The part of triangle (x, y) inside the square of half side `half` about (bx, by)
/// (Sutherland-Hodgman clipping, about the square's centre): its area and centroid.
struct Clipped {
  double area = 0, cx = 0, cy = 0;
};
Clipped ClipToBox(const double x[3], const double y[3], double bx, double by, double half) {
  double px[2][10], py[2][10];
  int n = 3, cur = 0;
  for (int q = 0; q < 3; ++q) px[0][q] = x[q] - bx, py[0][q] = y[q] - by;
  // Each side of the box: keep where s * (coordinate - bound) >= 0.
  const double bound[4] = {-half, half, -half, half};
  for (int side = 0; side < 4 && n > 0; ++side) {
    const bool along_x = side < 2;
    const double s = side % 2 == 0 ? 1 : -1, c = bound[side];
    const double* ix = px[cur];
    const double* iy = py[cur];
    double* ox = px[1 - cur];
    double* oy = py[1 - cur];
    int m = 0;
    for (int q = 0; q < n; ++q) {
      const int r = (q + 1) % n;
      const double dq = s * ((along_x ? ix[q] : iy[q]) - c);
      const double dr = s * ((along_x ? ix[r] : iy[r]) - c);
      if (dq >= 0) ox[m] = ix[q], oy[m] = iy[q], ++m;
      if ((dq >= 0) != (dr >= 0)) {
        const double f = dq / (dq - dr);
        ox[m] = ix[q] + f * (ix[r] - ix[q]), oy[m] = iy[q] + f * (iy[r] - iy[q]), ++m;
      }
    }
    n = m, cur = 1 - cur;
  }
  Clipped out;
  if (n < 3) return out;
  const double* cx = px[cur];
  const double* cy = py[cur];
  double a2 = 0, mx = 0, my = 0;
  for (int q = 0; q < n; ++q) {
    const int r = (q + 1) % n;
    const double cr = cx[q] * cy[r] - cx[r] * cy[q];
    a2 += cr, mx += (cx[q] + cx[r]) * cr, my += (cy[q] + cy[r]) * cr;
  }
  if (a2 == 0) return out;
  out.area = 0.5 * std::abs(a2), out.cx = bx + mx / (3 * a2), out.cy = by + my / (3 * a2);
  return out;
}

/// Adds the triangles' field to the plane's rows [r0, r1) (rows wrap: the grid is periodic).
/// Each node takes a triangle's field in the share of its cell (a node step square about it)
/// that the triangle covers: the barycentric mean of its rays' fields at the covered part's
/// centroid, with their phases carried to the node along their own wave vectors (second
/// order), times the tube's amplitude. A node deep inside a sheet takes its field at the node;
/// at a sheet's edge or fold the shares change continuously as the edge moves across the nodes,
/// so the image changes continuously with the objects. Returns the flux through the plane that
/// the nodes carry, each triangle's own (share times |E|^2 cos theta h^2; where sheets overlap,
/// without their interference). Only the triangles `which` (indices into tris, ascending) are
/// added.
double Rasterise(const std::vector<Tri>& tris, const std::vector<uint32_t>& which,
                 const PlaneGrid& pg, int r0, int r1, std::vector<CVec3>* field) {
  double flux = 0;
  const int n = pg.n;
  const double half = 0.5 * pg.h, cell = pg.h * pg.h;
  auto wrap = [n](int i) { return ((i % n) + n) % n; };
  for (const uint32_t index : which) {
    const Tri& t = tris[index];
    int jl, jh;
    RowsOf(t, pg, &jl, &jh);
    if (jl > jh) continue;
    const double x_lo = std::min({t.px[0], t.px[1], t.px[2]}) - half;
    const double x_hi = std::max({t.px[0], t.px[1], t.px[2]}) + half;
    const int il = int(std::ceil((x_lo - pg.x_lo) / pg.h));
    const int ih = int(std::floor((x_hi - pg.x_lo) / pg.h));
    if (il > ih) continue;
    const double s2 =
        (t.px[1] - t.px[0]) * (t.py[2] - t.py[0]) - (t.py[1] - t.py[0]) * (t.px[2] - t.px[0]);
    // Edge functions, positive inside: the box lies inside where they are at its worst corner.
    double ea[3], eb[3], ec[3];
    for (int q = 0; q < 3; ++q) {
      const int r = (q + 1) % 3;
      const double sign = s2 > 0 ? 1 : -1;
      ea[q] = -sign * (t.py[r] - t.py[q]), eb[q] = sign * (t.px[r] - t.px[q]);
      ec[q] = -(ea[q] * t.px[q] + eb[q] * t.py[q]);
    }
    for (int j = jl; j <= jh; ++j) {
      const int row = wrap(j);
      if (row < r0 || row >= r1) continue;
      const double y = pg.y_lo + j * pg.h;
      for (int i = il; i <= ih; ++i) {
        const double x = pg.x_lo + i * pg.h;
        bool inside = true;
        for (int q = 0; q < 3 && inside; ++q)
          inside = ea[q] * x + eb[q] * y + ec[q] - half * (std::abs(ea[q]) + std::abs(eb[q])) >= 0;
        double share = 1, sx = x, sy = y;
        if (!inside) {
          const Clipped c = ClipToBox(t.px, t.py, x, y, half);
          if (!(c.area > 0)) continue;
          share = c.area / cell, sx = c.cx, sy = c.cy;
        }
        double wb[3];
        wb[0] = ((t.px[1] - sx) * (t.py[2] - sy) - (t.py[1] - sy) * (t.px[2] - sx)) / s2;
        wb[1] = ((t.px[2] - sx) * (t.py[0] - sy) - (t.py[2] - sy) * (t.px[0] - sx)) / s2;
        wb[2] = 1 - wb[0] - wb[1];
        if (!inside) {  // (a sliver's centroid can round outside the triangle)
          for (double& v : wb) v = std::max(v, 0.0);
          const double sum = wb[0] + wb[1] + wb[2];
          for (double& v : wb) v /= sum;
        }
        double phi = 0, cos = 0, g = 0;
        CVec3 e{};
        for (int q = 0; q < 3; ++q) {
          phi += wb[q] * (t.phi[q] + t.kx[q] * (x - t.px[q]) + t.ky[q] * (y - t.py[q]));
          cos += wb[q] * t.cos[q];
          g += wb[q] * t.gv[q];
          for (int c = 0; c < 3; ++c) e[c] += wb[q] * t.e[q][c];
        }
        const C f = g / std::sqrt(cos) * std::exp(C(0, phi + t.focal_phase));
        CVec3& out = (*field)[size_t(row) * n + wrap(i)];
        for (int c = 0; c < 3; ++c) out[c] += share * f * e[c];
        flux += share * std::norm(f) * cos * (std::norm(e[0]) + std::norm(e[1]) + std::norm(e[2]));
      }
    }
  }
  return flux * pg.h * pg.h;
}

/// Calls f(j * nx + i, kx, ky, kz) for the grid's nodes within k_max (and below k), rows in
/// parallel.
template <class F>
void ForEachPassedNode(const SpectrumGrid& g, double k, F&& f) {
  tbb::parallel_for(0, g.ny, [&](int j) {
    const double ky = g.ky0 + j * g.dk;
    for (int i = 0; i < g.nx; ++i) {
      const double kx = g.kx0 + i * g.dk, kt2 = kx * kx + ky * ky;
      if (kt2 > g.k_max * g.k_max || kt2 >= k * k) continue;
      f(size_t(j) * g.nx + i, kx, ky, std::sqrt(k * k - kt2));
    }
  });
}

/// Adds the part of f e transverse to the unit vector u to a.
void AddTransverse(const C& f, const CVec3& e, const Vec3& u, CVec3* a) {
  const C along = e[0] * u.x + e[1] * u.y + e[2] * u.z;
  (*a)[0] += f * (e[0] - along * u.x);
  (*a)[1] += f * (e[1] - along * u.y);
  (*a)[2] += f * (e[2] - along * u.z);
}

/// Adds the angular spectrum of the plane's field, (h^2 / (2 pi)^2) sum E(x) exp(-i k_t . x),
/// at the grid's nodes (transverse parts only), by one DFT per component of the field
/// modulated by exp(-i k_0 . x) (k_0 the grid's first node).
void AddPlaneSpectrum(const std::vector<CVec3>& field, const PlaneGrid& pg, const SpectrumGrid& g,
                      double k, double dz, RaySpectrum* out) {
  const int n = pg.n;
  std::array<cv::Mat, 3> m;
  for (int c = 0; c < 3; ++c) m[c].create(n, n, CV_64FC2);
  tbb::parallel_for(0, n, [&](int q) {
    const double y = pg.y_lo + q * pg.h;
    for (int p = 0; p < n; ++p) {
      const double x = pg.x_lo + p * pg.h;
      const C mod = std::exp(C(0, -(g.kx0 * x + g.ky0 * y)));
      for (int c = 0; c < 3; ++c) {
        const C v = field[size_t(q) * n + p][c] * mod;
        m[c].at<cv::Vec2d>(q, p) = cv::Vec2d(v.real(), v.imag());
      }
    }
  });
  for (int c = 0; c < 3; ++c) cv::dft(m[c], m[c]);  // forward: sum exp(-2 pi i (p i + q j) / n)
  const double scale = pg.h * pg.h / (4 * M_PI * M_PI);
  ForEachPassedNode(g, k, [&](size_t p, double kx, double ky, double kz) {
    const C shift =
        scale * std::exp(C(0, -((kx - g.kx0) * pg.x_lo + (ky - g.ky0) * pg.y_lo) - kz * dz));
    const int i = int(p % size_t(g.nx)), j = int(p / size_t(g.nx));
    CVec3 e;
    for (int c = 0; c < 3; ++c) {
      const cv::Vec2d v = m[c].at<cv::Vec2d>(j % n, i % n);
      e[c] = C(v[0], v[1]);
    }
    AddTransverse(shift, e, Vec3(kx / k, ky / k, kz / k), &out->a[p]);
  });
}

/// The silhouette's outline on the start plane: oriented segments (the shadow on their left).
class Outline {
 public:
  Outline(const Wave& w, const Lattice& lat, int levels) : w_(w), lat_(lat), levels_(levels) {}

  std::vector<std::array<double, 4>> Segments() {
    const int64_t nx = lat_.ni + 1, ny = lat_.nj + 1;
    std::vector<char> hit(size_t(nx * ny));
    tbb::parallel_for(int64_t(0), ny, [&](int64_t j) {
      for (int64_t i = 0; i < nx; ++i) hit[size_t(j * nx + i)] = Hits(i * lat_.step, j * lat_.step);
    });
    // Coarse cells whose corners differ, and every cell next to one, are marched at the finest
    // level throughout: two cells that share an edge then find the outline's crossings of it
    // on the same finest edges. (Refined only where their own corners differ, a cell next to
    // a coarser one would cross the shared edge where the coarse cell does not, and the outline
    // would not close: at a polygon's corner that pokes through a coarse edge between two
    // nodes outside it.)
    auto mixed = [&](int64_t ci, int64_t cj) {
      if (ci < 0 || cj < 0 || ci >= lat_.ni || cj >= lat_.nj) return false;
      const char a = hit[size_t(cj * nx + ci)];
      return hit[size_t(cj * nx + ci + 1)] != a || hit[size_t((cj + 1) * nx + ci + 1)] != a ||
             hit[size_t((cj + 1) * nx + ci)] != a;
    };
    std::vector<std::vector<std::array<double, 4>>> rows(size_t(lat_.nj));
    tbb::parallel_for(int64_t(0), lat_.nj, [&](int64_t cj) {
      for (int64_t ci = 0; ci < lat_.ni; ++ci) {
        bool near = false;
        for (int64_t dj = -1; dj <= 1 && !near; ++dj)
          for (int64_t di = -1; di <= 1 && !near; ++di) near = mixed(ci + di, cj + dj);
        if (!near) continue;
        const bool c[4] = {bool(hit[size_t(cj * nx + ci)]), bool(hit[size_t(cj * nx + ci + 1)]),
                           bool(hit[size_t((cj + 1) * nx + ci + 1)]),
                           bool(hit[size_t((cj + 1) * nx + ci)])};
        Cell(ci * lat_.step, cj * lat_.step, lat_.step, c, &rows[size_t(cj)]);
      }
    });
    std::vector<std::array<double, 4>> all;
    for (const auto& r : rows) all.insert(all.end(), r.begin(), r.end());
    return all;
  }

 private:
  bool Hits(int64_t i, int64_t j) const { return HitsAt(lat_.Start(i, j)); }
  bool HitsAt(const Vec3& s) const {
    return w_.sim->TraceFieldRay(s, w_.din, w_.e0, 0, 1).events > 0;
  }

  /// The outline's crossing of the lattice edge from (i0, j0) to (i1, j1), by bisection from
  /// the lower key's end (the same point for both cells that share the edge).
  std::array<double, 2> Crossing(int64_t i0, int64_t j0, int64_t i1, int64_t j1) const {
    if (lat_.Key(i1, j1) < lat_.Key(i0, j0)) std::swap(i0, i1), std::swap(j0, j1);
    const Vec3 a = lat_.Start(i0, j0), b = lat_.Start(i1, j1);
    const bool in_a = HitsAt(a);
    double lo = 0, hi = 1;
    for (int it = 0; it < 30; ++it) {
      const double mid = 0.5 * (lo + hi);
      (HitsAt(a + (b - a) * mid) == in_a ? lo : hi) = mid;
    }
    const Vec3 p = a + (b - a) * (0.5 * (lo + hi));
    return {p.x, p.y};
  }

  /// Cell (i, j) of side s, corners c, split down to the finest level; the finest cells whose
  /// corners differ are marched.
  void Cell(int64_t i, int64_t j, int64_t s, const bool c[4],
            std::vector<std::array<double, 4>>* out) const {
    if (s > (lat_.step >> levels_)) {
      const int64_t h = s / 2;
      const bool m[5] = {Hits(i + h, j), Hits(i + s, j + h), Hits(i + h, j + s), Hits(i, j + h),
                         Hits(i + h, j + h)};
      const bool q00[4] = {c[0], m[0], m[4], m[3]}, q10[4] = {m[0], c[1], m[1], m[4]};
      const bool q11[4] = {m[4], m[1], c[2], m[2]}, q01[4] = {m[3], m[4], m[2], c[3]};
      Cell(i, j, h, q00, out);
      Cell(i + h, j, h, q10, out);
      Cell(i + h, j + h, h, q11, out);
      Cell(i, j + h, h, q01, out);
      return;
    }
    if (c[0] == c[1] && c[1] == c[2] && c[2] == c[3]) return;
    // Marching squares: corners counter-clockwise; crossings in that order around the cell.
    const int64_t ci[4] = {i, i + s, i + s, i}, cj[4] = {j, j, j + s, j + s};
    struct X {
      std::array<double, 2> p;
      bool into;  // the walk enters the shadow here
    };
    X xs[4];
    int n = 0;
    for (int q = 0; q < 4; ++q) {
      const int r = (q + 1) % 4;
      if (c[q] != c[r]) xs[n++] = {Crossing(ci[q], cj[q], ci[r], cj[r]), c[r]};
    }
    // A saddle's centre decides whether the shadow joins across it.
    const bool centre_in = n == 4 && Hits(i + s / 2, j + s / 2);
    for (int q = 0; q < n; ++q) {
      if (xs[q].into) continue;
      // Leaving the shadow at q: the outline runs back to the previous entry, or on to the
      // next one when the shadow joins across a saddle.
      const X& to = centre_in ? xs[(q + 1) % n] : xs[(q + n - 1) % n];
      out->push_back({xs[q].p[0], xs[q].p[1], to.p[0], to.p[1]});
    }
  }

  const Wave& w_;
  const Lattice& lat_;
  int levels_;
};

/// The integral of exp(-i q . x) over the region the segments enclose (the region on their
/// left), by Green's theorem: (i / q^2) sum over segments of (q_x e_y - q_y e_x) exp(-i q . a)
/// (exp(-i q . e) - 1) / (-i q . e); near q = 0 its Taylor series to second order from the
/// region's moments.
struct RegionTransform {
  std::vector<std::array<double, 4>> seg;
  double area = 0, mx = 0, my = 0, mxx = 0, mxy = 0, myy = 0, r_max = 0;

  explicit RegionTransform(std::vector<std::array<double, 4>> s) : seg(std::move(s)) {
    // Green: integral of f dA = closed integral of F dy with dF/dx = f, by 3-point
    // Gauss-Legendre along each segment (exact: F dy is at most cubic).
    const double gx[3] = {0.5 - std::sqrt(0.15), 0.5, 0.5 + std::sqrt(0.15)};
    const double gw[3] = {5.0 / 18, 8.0 / 18, 5.0 / 18};
    for (const auto& e : seg) {
      const double dy = e[3] - e[1];
      for (int q = 0; q < 3; ++q) {
        const double x = e[0] + (e[2] - e[0]) * gx[q], y = e[1] + dy * gx[q], w = gw[q] * dy;
        area += w * x, mx += w * x * x / 2, my += w * x * y;
        mxx += w * x * x * x / 3, mxy += w * x * x * y / 2, myy += w * x * y * y;
      }
      r_max = std::max({r_max, std::hypot(e[0], e[1]), std::hypot(e[2], e[3])});
    }
  }

  /// The Taylor series to second order from the region's moments, for |q| r_max < 0.02.
  C NearZero(double qx, double qy) const {
    return C(area - 0.5 * (qx * qx * mxx + 2 * qx * qy * mxy + qy * qy * myy),
             -(qx * mx + qy * my));
  }

  /// The transform on a row of nodes q = (qx0 + i dq, qy), i = 0 ... n - 1, into out[i], with
  /// each segment's end phasors exp(-i q . a), exp(-i q . b) stepped along the row (one
  /// complex product a node instead of an exponential and a complex division):
  /// exp(-i q . a) (exp(-i q . e) - 1) / (-i q . e) = i (exp(-i q . b) - exp(-i q . a)) / (q . e).
  void Row(double qx0, double dq, double qy, int n, C* out) const {
    std::vector<C> sum(static_cast<size_t>(n), C(0));
    for (const auto& e : seg) {
      const double ex = e[2] - e[0], ey = e[3] - e[1];
      C pa = std::exp(C(0, -(qx0 * e[0] + qy * e[1]))),
        pb = std::exp(C(0, -(qx0 * e[2] + qy * e[3])));
      const C sa = std::exp(C(0, -dq * e[0])), sb = std::exp(C(0, -dq * e[2]));
      double u = qx0 * ex + qy * ey, w = qx0 * ey - qy * ex;
      for (int i = 0; i < n; ++i) {
        if (std::abs(u) < 1e-3) {
          sum[size_t(i)] += w * pa * C(1 - u * u / 6, -u / 2 + u * u * u / 24);
        } else {
          sum[size_t(i)] += (w / u) * C(0, 1) * (pb - pa);
        }
        pa *= sa, pb *= sb, u += dq * ex, w += dq * ey;
      }
    }
    for (int i = 0; i < n; ++i) {
      const double qx = qx0 + i * dq, q2 = qx * qx + qy * qy;
      out[i] = std::sqrt(q2) * r_max < 0.02 ? NearZero(qx, qy) : C(0, 1) / q2 * sum[size_t(i)];
    }
  }
};

/// The lattice over the objects' shadow on the start plane (a spacing beyond it), or as
/// `layout` lays it out (FieldLayout; recording it when it is empty or the box outgrew it).
Lattice MakeLattice(const Simulator& sim, const Vec3& din, double spacing, int levels,
                    FieldLayout* layout) {
  const auto bounds = sim.ObjectBounds();
  RAYMATCH_CHECK(!bounds.empty());
  double z_lo = kInf;
  for (const auto& [c, r] : bounds) z_lo = std::min(z_lo, c.z - r);
  Lattice lat;
  lat.z_start = z_lo - 1.0;
  double box[4] = {kInf, kInf, -kInf, -kInf};
  for (const auto& [c, r] : bounds) {
    // The bounding sphere's shadow on the start plane, along din: within r / din.z of the
    // projected centre.
    const double t = (c.z - lat.z_start) / din.z;
    const double cx = c.x - din.x * t, cy = c.y - din.y * t, rr = r / din.z;
    box[0] = std::min(box[0], cx - rr), box[2] = std::max(box[2], cx + rr);
    box[1] = std::min(box[1], cy - rr), box[3] = std::max(box[3], cy + rr);
  }
  lat.step = int64_t(1) << levels;
  if (layout && layout->recorded) {
    const double* b0 = layout->box;
    const double a = (box[2] - box[0] + box[3] - box[1]) / (b0[2] - b0[0] + b0[3] - b0[1]);
    const double sp = layout->spacing * a;
    lat.x_lo = 0.5 * (box[0] + box[2]) - (0.5 * (b0[0] + b0[2]) - layout->x_lo) * a;
    lat.y_lo = 0.5 * (box[1] + box[3]) - (0.5 * (b0[1] + b0[3]) - layout->y_lo) * a;
    lat.ni = layout->ni, lat.nj = layout->nj;
    lat.h = sp / double(lat.step);
    if (lat.x_lo < box[0] && lat.y_lo < box[1] && lat.x_lo + double(lat.ni) * sp > box[2] &&
        lat.y_lo + double(lat.nj) * sp > box[3])
      return lat;
    *layout = FieldLayout{};  // outgrown: laid out afresh
  }
  lat.h = spacing / double(lat.step);
  lat.x_lo = box[0] - spacing, lat.y_lo = box[1] - spacing;
  lat.ni = int64_t(std::ceil((box[2] - box[0]) / spacing + 2));
  lat.nj = int64_t(std::ceil((box[3] - box[1]) / spacing + 2));
  if (layout) {
    layout->ni = lat.ni, layout->nj = lat.nj, layout->spacing = spacing;
    layout->x_lo = lat.x_lo, layout->y_lo = lat.y_lo;
    std::copy(box, box + 4, layout->box);
    layout->halved.clear();
  }
  return lat;
}

/// Adds the shadow's spectrum, -(E0 / (2 pi)^2) times the silhouette's transform at
/// q = k_t - k_in,t, on the origin's z-plane.
/// The silhouette's transform at q = k_t - k_in,t on the grid's nodes, on the origin's z-plane,
/// with its area and outline; the same for every polarisation of a direction.
struct Shadow {
  std::vector<C> transform;
  double area = 0;
  int segments = 0;
};

Shadow ShadowOf(const Wave& w, const Lattice& lat, const SpectrumGrid& g) {
  Outline outline(w, lat, std::min<int>(3, int(std::log2(double(lat.step)))));
  std::vector<std::array<double, 4>> seg = outline.Segments();
  // Start plane to the origin's plane along din, relative to the origin.
  const double t = (w.origin.z - lat.z_start) / w.din.z;
  const double sx = w.din.x * t - w.origin.x, sy = w.din.y * t - w.origin.y;
  for (auto& e : seg) e[0] += sx, e[1] += sy, e[2] += sx, e[3] += sy;
  const RegionTransform region(std::move(seg));
  Shadow sh;
  sh.area = region.area;
  sh.segments = int(region.seg.size());
  const double kin_x = w.k * w.din.x, kin_y = w.k * w.din.y;
  sh.transform.resize(size_t(g.nx) * g.ny);
  tbb::parallel_for(0, g.ny, [&](int j) {
    region.Row(g.kx0 - kin_x, g.dk, g.ky0 + j * g.dk - kin_y, g.nx,
               &sh.transform[size_t(j) * g.nx]);
  });
  return sh;
}

/// Adds the shadow's spectrum, -(E0 / (2 pi)^2) times the silhouette's transform.
void AddShadow(const Wave& w, const SpectrumGrid& g, const Shadow& sh, RaySpectrum* out) {
  out->shadow_area_um2 = sh.area;
  out->outline_segments = sh.segments;
  const double k = w.k;
  ForEachPassedNode(g, k, [&](size_t p, double kx, double ky, double kz) {
    const C f = -sh.transform[p] / (4 * M_PI * M_PI);
    AddTransverse(f, w.e0, Vec3(kx / k, ky / k, kz / k), &out->a[p]);
  });
}

/// Each ray's tube amplitude, sqrt(dA_in / dA_plane) over the triangles of its branch that share
/// it (their areas summed): interpolated across a triangle, the field is continuous from one
/// triangle to the next, so a plane node that crosses from one into another as the objects
/// change sees no jump (a triangle's own amplitude would jump at every edge).
void VertexAmplitudes(std::vector<Tri>* tris) {
  std::unordered_map<uint64_t, std::pair<double, double>> sum;  // ray -> (dA_in, dA_plane)
  sum.reserve(tris->size() * 2);
  for (const Tri& t : *tris)
    for (uint64_t id : t.id) {
      auto& [in, plane] = sum[id];
      in += t.area_in, plane += t.area_p;
    }
  for (Tri& t : *tris)
    for (int q = 0; q < 3; ++q) {
      const auto& [in, plane] = sum.at(t.id[q]);
      t.gv[q] = std::sqrt(in / plane);
    }
}

/// Adds the branches' spectrum (every reflect/refract sequence up to max_events surfaces) to
/// `out`, with their rays, triangles and powers.
/// With `layout`, each branch's halved edges are replayed from it (FieldLayout::recorded) or
/// recorded into it.
void AddBranches(const Wave& w, const Lattice& lat, const SpectrumGrid& grid, const PlaneGrid& pg,
                 const RaySpectrumSettings& set, FieldLayout* layout, RaySpectrum* out_ptr) {
  RaySpectrum& out = *out_ptr;
  // The branches, shortest first: a branch of m events grows into m + 1 only where its rays
  // meet another surface.
  std::vector<Branch> open = {{0, 0}};
  std::vector<Tri> tris;
  for (int m = 1; m <= set.max_events && !open.empty(); ++m) {
    std::vector<Branch> next;
    for (const Branch& parent : open)
      for (uint32_t bit = 0; bit < 2; ++bit) {
        const Branch br{parent.mask | (bit << (m - 1)), m};
        const std::vector<uint64_t>* replay = nullptr;
        std::vector<uint64_t>* record = nullptr;
        if (layout) {
          std::vector<uint64_t>& halved = layout->halved[uint64_t(br.mask) | uint64_t(m) << 32];
          if (layout->recorded) {
            replay = &halved;
          } else {
            record = &halved;
          }
        }
        BranchMapper mapper(w, lat, grid, pg, set, br, replay, record);
        std::vector<Tri> bt;
        bool goes_on = false;
        if (mapper.Run(&bt, &goes_on, &out.rays, &out.branch_power)) {
          ++out.branches;
          VertexAmplitudes(&bt);
          tris.insert(tris.end(), bt.begin(), bt.end());
        }
        if (goes_on) next.push_back(br);
      }
    open = std::move(next);
  }
  out.triangles = tris.size();
  std::vector<CVec3> field(size_t(pg.n) * pg.n, CVec3{});
  // Bands of rows, each with the triangles that reach it (in their order, so each node sums
  // its triangles in the same order whatever the bands).
  constexpr int kRows = 8;
  const int bands = (pg.n + kRows - 1) / kRows;
  std::vector<std::vector<uint32_t>> in_band(static_cast<size_t>(bands));
  for (size_t t = 0; t < tris.size(); ++t) {
    int jl, jh;
    RowsOf(tris[t], pg, &jl, &jh);
    if (jl > jh) continue;
    auto band = [&](int j) { return (((j % pg.n) + pg.n) % pg.n) / kRows; };
    if (int64_t(jh) - jl + 1 >= pg.n) {
      for (auto& b : in_band) b.push_back(uint32_t(t));
      continue;
    }
    int last = -1;
    for (int j = jl; j <= jh; ++j)  // rows wrap: a band may come round again
      if (const int b = band(j); b != last) {
        if (in_band[size_t(b)].empty() || in_band[size_t(b)].back() != uint32_t(t))
          in_band[size_t(b)].push_back(uint32_t(t));
        last = b;
      }
  }
  std::vector<double> flux(static_cast<size_t>(bands), 0.0);
  tbb::parallel_for(0, bands, [&](int b) {
    flux[size_t(b)] =
        Rasterise(tris, in_band[size_t(b)], pg, b * kRows, std::min(pg.n, (b + 1) * kRows), &field);
  });
  for (double f : flux) out.plane_power += f;
  AddPlaneSpectrum(field, pg, grid, w.k, w.plane_z - w.origin.z, &out);
}

}  // namespace

std::vector<RaySpectrum> RayAngularSpectra(const Simulator& sim, const Vec3& direction,
                                           const std::vector<CVec3>& e0s, const Vec3& origin,
                                           const SpectrumGrid& grid, const RaySpectrumSettings& set,
                                           FieldLayout* layout) {
  const Scene& scene = sim.scene();
  Wave w;
  w.sim = &sim;
  w.din = Normalize(direction);
  w.origin = origin;
  w.k0 = 2 * M_PI / scene.wavelength_um;
  w.k = w.k0 * scene.medium_index;
  w.n_medium = scene.medium_index;
  RAYMATCH_CHECK(w.din.z > 0 && grid.nx > 0 && grid.ny > 0 && grid.dk > 0);
  RAYMATCH_CHECK(set.taper > 0 && set.plane_oversample >= 1 && set.max_events >= 0 &&
                 set.max_events <= Simulator::FieldRay::kMaxEvents);
  RAYMATCH_CHECK(set.refine_levels >= 0 && set.refine_levels <= 20);
  std::vector<RaySpectrum> all(e0s.size());
  for (RaySpectrum& out : all) out.a.assign(size_t(grid.nx) * grid.ny, CVec3{});
  if (scene.objects.empty() || e0s.empty()) return all;
  const double spacing =
      set.ray_spacing_um > 0 ? set.ray_spacing_um : scene.wavelength_um / scene.medium_index;
  const Lattice lat = MakeLattice(sim, w.din, spacing, set.refine_levels, layout);
  w.plane_z = origin.z + set.exit_plane_um;
  // The branches' rays pass up to the grid's k_max, then taper off.
  w.k_pass = std::min(grid.k_max, w.k);
  w.k_taper = std::min(set.taper * grid.k_max, 0.5 * (w.k - w.k_pass) + 1e-9);
  PlaneGrid pg;
  const double window = 2 * M_PI / grid.dk;
  const double h_max = M_PI / (w.k_pass + w.k_taper) / 1.25;
  // Finer than the band needs: the error of a sheet's edge sampled by its covered shares falls
  // with the step.
  pg.n = cv::getOptimalDFTSize(
      std::max({grid.nx, grid.ny, int(std::ceil(set.plane_oversample * window / h_max))}));
  pg.h = window / pg.n;
  pg.cell = h_max;
  pg.x_lo = pg.y_lo = -0.5 * window;
  w.e0 = e0s[0];  // (the outline's rays carry a field, but only their hits count)
  const Shadow shadow = ShadowOf(w, lat, grid);
  for (size_t q = 0; q < e0s.size(); ++q) {
    w.e0 = e0s[q];
    AddShadow(w, grid, shadow, &all[q]);
    AddBranches(w, lat, grid, pg, set, layout, &all[q]);
    if (layout) layout->recorded = true;  // the other polarisations replay the first's
  }
  return all;
}

RaySpectrum RayAngularSpectrum(const Simulator& sim, const Vec3& direction, const CVec3& e0,
                               const Vec3& origin, const SpectrumGrid& grid,
                               const RaySpectrumSettings& set) {
  return RayAngularSpectra(sim, direction, {e0}, origin, grid, set)[0];
}

}  // namespace raymatch::simulate
