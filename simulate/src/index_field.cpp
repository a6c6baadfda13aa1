#include "raymatch/simulate/index_field.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>

#include "grin_cells.h"

namespace raymatch::simulate {

namespace {

// Cell index and fraction along one axis (x in sample units); outside [0, n-1] the value is
// held constant (fraction clamped) and `inside` is false so the gradient along it is zero.
inline void Locate(double x, int n, int* i, double* f, bool* inside) {
  if (n < 2 || x < 0) {
    *i = 0, *f = 0, *inside = false;
  } else if (x >= n - 1) {
    *i = n - 2, *f = 1, *inside = false;
  } else {
    *i = static_cast<int>(x), *f = x - *i, *inside = true;
  }
}

}  // namespace

void IndexField::EvalUnrotated(const Vec3& p, double* n, Vec3* grad) const {
  switch (type) {
    case IndexFieldType::kLuneburg: {
      const double q = 2 - Dot(p, p) / (radius_um * radius_um);
      const double nn = n0 * std::sqrt(std::max(q, 1e-12));
      *n = nn;
      *grad = p * (-n0 * n0 / (radius_um * radius_um) / nn);  // grad n = grad(n^2) / 2n
      return;
    }
    case IndexFieldType::kFishEye: {
      const double a2 = radius_um * radius_um, den = 1 + Dot(p, p) / a2;
      *n = n0 / den;
      *grad = p * (-2 * n0 / (a2 * den * den));
      return;
    }
    case IndexFieldType::kParabolic: {
      const double g2 = g_per_um * g_per_um;
      const double n2 = n0 * n0 * (1 - g2 * (p.x * p.x + p.y * p.y));
      const double nn = std::sqrt(std::max(n2, 1e-12));
      *n = nn;
      *grad = Vec3(p.x, p.y, 0) * (-n0 * n0 * g2 / nn);
      return;
    }
    case IndexFieldType::kLinearN2: {
      const double nn = std::sqrt(std::max(n0 * n0 + Dot(k_per_um, p), 1e-12));
      *n = nn;
      *grad = k_per_um * (0.5 / nn);
      return;
    }
    case IndexFieldType::kGridRZ: {
      const double r = std::sqrt(p.x * p.x + p.y * p.y);
      int ir, iz;
      double fr, fz;
      bool in_r, in_z;
      Locate((r - origin_um.x) / spacing_um.x, nx, &ir, &fr, &in_r);
      Locate((p.z - origin_um.z) / spacing_um.z, nz, &iz, &fz, &in_z);
      const double* grid_values = grid();
      auto v = [&](int a, int b) {  // a: z index, b: r index
        const double x = grid_values[size_t(std::min(a, nz - 1)) * nx + std::min(b, nx - 1)];
        return mapped_ ? map_offset_ + map_scale_ * x : x;
      };
      const double v00 = v(iz, ir), v01 = v(iz, ir + 1), v10 = v(iz + 1, ir),
                   v11 = v(iz + 1, ir + 1);
      const double a0 = v00 + (v01 - v00) * fr, a1 = v10 + (v11 - v10) * fr;
      *n = a0 + (a1 - a0) * fz;
      const double dn_dr = in_r ? ((v01 - v00) * (1 - fz) + (v11 - v10) * fz) / spacing_um.x : 0.0;
      const double dn_dz = in_z ? (a1 - a0) / spacing_um.z : 0.0;
      // On the axis dn/dr is taken as 0 (the field is smooth and symmetric there).
      const Vec3 radial = r > 1e-12 ? Vec3(p.x / r, p.y / r, 0) : Vec3();
      *grad = radial * dn_dr + Vec3(0, 0, dn_dz);
      return;
    }
    case IndexFieldType::kGrid3D: {
      // One implementation for single evaluations and the cell-by-cell integrator.
      EvalInCell(Cell(p), p, n, grad);
      return;
    }
  }
}

IndexField IndexField::AffineView() const {
  IndexField v;
  v.type = type, v.n0 = n0, v.radius_um = radius_um, v.g_per_um = g_per_um, v.k_per_um = k_per_um;
  v.nx = nx, v.ny = ny, v.nz = nz, v.origin_um = origin_um, v.spacing_um = spacing_um;
  v.min_n = min_n, v.max_n = max_n;
  v.rotated = rotated, v.rotation = rotation, v.rotation_t = rotation_t;
  v.shared_ = grid();
  v.mapped_ = true;
  return v;
}

double IndexField::MaxStepUm() const {
  switch (type) {
    case IndexFieldType::kGridRZ:
      return 0.5 * std::min(spacing_um.x, spacing_um.z);
    case IndexFieldType::kGrid3D:
      return 0.5 * std::min({spacing_um.x, spacing_um.y, spacing_um.z});
    default:
      return 0;
  }
}

namespace {

// Extent and stride of a cell along one axis of `count` samples from its index k (-1: before the
// first sample, count - 1: beyond the last). Beyond the samples (or along an axis with one) the
// field is constant along the axis: stride 0, so that its terms vanish, and the cell reaches to
// infinity there.
void SetAxis(int count, int k, size_t full, double* lo, double* hi, size_t* stride) {
  constexpr double kInf = std::numeric_limits<double>::infinity();
  const bool interior = count >= 2 && k >= 0 && k <= count - 2;
  *stride = interior ? full : 0;
  *lo = count < 2 || k < 0 ? -kInf : 0;
  *hi = count < 2 || k >= count - 1 ? kInf : (k < 0 ? 0 : 1);
}

}  // namespace

GridCell IndexField::Cell(const Vec3& p) const {
  return CellWith(p, {1 / spacing_um.x, 1 / spacing_um.y, 1 / spacing_um.z});
}

GridCell IndexField::CellWith(const Vec3& p, const Vec3& inv_spacing) const {
  GridCell g;
  g.at = p;
  g.inv_spacing = inv_spacing;
  const int count[3] = {nx, ny, nz};
  const double o[3] = {origin_um.x, origin_um.y, origin_um.z};
  for (int a = 0; a < 3; ++a) {
    const double u = (p[a] - o[a]) * inv_spacing[a];
    // -1 before the first sample (or not a number), count - 1 beyond the last.
    g.k[a] = !(u >= 0) ? -1 : u >= count[a] - 1 ? count[a] - 1 : static_cast<int>(u);
  }
  Fill(&g);
  return g;
}

void IndexField::NextCell(const GridCell& g, int a, int side, GridCell* next) const {
  // The same cell but for axis a: one node further, and the same strides but for that axis.
  *next = g;
  const int n = a == 0 ? nx : a == 1 ? ny : nz;
  const size_t full = a == 0 ? 1 : a == 1 ? size_t(nx) : size_t(nx) * size_t(ny);
  const int k = std::clamp(g.k[a] + side, -1, n - 1);
  const int i_old = std::clamp(g.k[a], 0, n - 1), i = std::clamp(k, 0, n - 1);
  next->k[a] = k;
  SetAxis(n, k, full, &next->lo[a], &next->hi[a], &next->stride[a]);
  switch (a) {
    case 0:
      next->node.x = origin_um.x + i * spacing_um.x;
      break;
    case 1:
      next->node.y = origin_um.y + i * spacing_um.y;
      break;
    default:
      next->node.z = origin_um.z + i * spacing_um.z;
      break;
  }
  next->base = g.base + size_t(ptrdiff_t(i - i_old) * ptrdiff_t(full));  // wraps like a signed step
  Corners(next);
}

void IndexField::Fill(GridCell* g) const {
  const int count[3] = {nx, ny, nz};
  const double o[3] = {origin_um.x, origin_um.y, origin_um.z};
  const double h[3] = {spacing_um.x, spacing_um.y, spacing_um.z};
  const size_t full[3] = {1, size_t(nx), size_t(nx) * size_t(ny)};
  double node[3];
  g->base = 0;
  for (int a = 0; a < 3; ++a) {
    const int i = std::clamp(g->k[a], 0, std::max(count[a] - 1, 0));
    SetAxis(count[a], g->k[a], full[a], &g->lo[a], &g->hi[a], &g->stride[a]);
    node[a] = o[a] + i * h[a];
    g->base += size_t(i) * full[a];
  }
  g->node = {node[0], node[1], node[2]};
  Corners(g);
}

void IndexField::Corners(GridCell* g) const {
  const double* b = grid() + g->base;
  const size_t sx = g->stride[0], sy = g->stride[1], sz = g->stride[2];
  double v000 = b[0], v100 = b[sx], v010 = b[sy], v110 = b[sy + sx], v001 = b[sz],
         v101 = b[sz + sx], v011 = b[sz + sy], v111 = b[sz + sy + sx];
  if (mapped_)  // equal corners stay equal: an axis of stride 0 still gives exact zeros
    for (double* v : {&v000, &v100, &v010, &v110, &v001, &v101, &v011, &v111})
      *v = map_offset_ + map_scale_ * *v;
  // Differences along x on the four x edges; grouped so that an axis of stride 0 gives exact
  // zeros for every coefficient that involves it.
  const double dx00 = v100 - v000, dx10 = v110 - v010, dx01 = v101 - v001, dx11 = v111 - v011;
  g->c[0] = v000;
  g->c[1] = dx00;
  g->c[2] = v010 - v000;
  g->c[3] = v001 - v000;
  g->c[4] = dx10 - dx00;
  g->c[5] = dx01 - dx00;
  g->c[6] = (v011 - v001) - (v010 - v000);
  g->c[7] = (dx11 - dx01) - (dx10 - dx00);
}

namespace {

// The smallest dt >= 0 with acc dt^2 / 2 + speed dt = dist (dist >= 0, speed >= 0 along the
// way to the face), without cancellation; +inf when the path turns back first. Where the
// curvature term is small (|acc dist| < 0.1 speed^2) the root's series to second order
// replaces the square root: dist/speed (1 - e/2 + e^2/2), e = acc dist / speed^2, relative
// error < e^3 (the caller lands the step on the face exactly afterwards).
double FaceStep(double dist, double speed, double acc) {
  const double r = 1 / speed, e = acc * dist * r * r;
  if (std::abs(e) < 0.1) return dist * r * (1 - e * 0.5 + e * e * 0.5);
  const double disc = speed * speed + 2 * acc * dist;
  if (disc < 0) return std::numeric_limits<double>::infinity();
  return 2 * dist / (speed + std::sqrt(disc));  // inf when speed = acc = 0
}

Vec3 CellCoordinates(const GridCell& g, const Vec3& p) {
  return {(p.x - g.node.x) * g.inv_spacing.x, (p.y - g.node.y) * g.inv_spacing.y,
          (p.z - g.node.z) * g.inv_spacing.z};
}

}  // namespace

CellExit PredictCellExit(const GridCell& g, const Vec3& p, const Vec3& t, const Vec3& d) {
  // In cell units: u(dt) = u0 + vel dt + acc dt^2 / 2 along each axis. The straight path picks
  // the face (without branches on which axis wins: the winner is close to random from step to
  // step), the curved one gives the step to it. Where the two orders of the faces differ (a
  // near-tie at an edge), the other face is crossed by a hair, which CellStep checks.
  constexpr double kInf = std::numeric_limits<double>::infinity();
  const Vec3 u = CellCoordinates(g, p), vel = Mul(t, g.inv_spacing), acc = Mul(d, g.inv_spacing);
  double straight[3], dist[3], side[3];
  for (int a = 0; a < 3; ++a) {
    // The face ahead (along the acceleration when the ray runs parallel to the faces).
    const bool up = vel[a] > 0 || (vel[a] == 0 && acc[a] > 0);
    const double face = up ? g.hi[a] : g.lo[a];
    side[a] = up ? 1.0 : -1.0;
    dist[a] = std::max(side[a] * (face - u[a]), 0.0) + kCellOvershoot;
    straight[a] = dist[a] / std::abs(vel[a]);  // +inf for a face at infinity or vel = 0
  }
  const int a01 = straight[1] < straight[0] ? 1 : 0;
  const int a = straight[2] < straight[a01] ? 2 : a01;
  CellExit e;
  if (straight[a] < kInf) {
    e = {FaceStep(dist[a], side[a] * vel[a], side[a] * acc[a]), a, int(side[a])};
  } else {
    // Parallel to every face it could reach: only the acceleration takes it there.
    for (int b = 0; b < 3; ++b) {
      const double face = side[b] > 0 ? g.hi[b] : g.lo[b];
      const double step = std::isinf(face) ? kInf : FaceStep(dist[b], 0.0, side[b] * acc[b]);
      if (step < e.dt) e = {step, b, int(side[b])};
    }
  }
  if (!(e.dt < kInf)) e = CellExit();
  return e;
}

namespace {

// D = n grad n = grad(n^2) / 2 at world point r.
Vec3 D(const IndexField& f, const Vec3& c, const Vec3& r) {
  double n;
  Vec3 g;
  f.Eval(r - c, &n, &g);
  return g * n;
}

// The last of Sharma's stages, from the first two (A = D(s.r) dt, B = D at the midpoint x dt),
// with `d_at(r)` = D at world point r: the state after dt and (optional) the embedded estimate.
// `d_end` (optional) receives the last stage's D, taken at r + T dt + B dt / 2 (the step's end
// to O(dt^2)).
// kSixth: multiply by 1/6 instead of dividing by 6 (the cell path, which owes no bit-identity
// to earlier builds; a division costs what a dozen multiplications do).
template <bool kSixth = false, class DAt>
GrinState SharmaFinish(DAt&& d_at, const GrinState& s, const Vec3& A, const Vec3& B, double dt,
                       double* err, Vec3* d_end = nullptr) {
  const Vec3 d_c = d_at(s.r + s.t * dt + B * (dt / 2));
  if (d_end) *d_end = d_c;
  const Vec3 C = d_c * dt;
  if constexpr (kSixth) {
    constexpr double k = 1.0 / 6;
    if (err) *err = Length(A - B * 2 + C) * (std::abs(dt) * k);
    return {s.r + (s.t + (A + B * 2) * k) * dt, s.t + (A + B * 4 + C) * k};
  } else {
    if (err) *err = Length(A - B * 2 + C) * (std::abs(dt) / 6);
    return {s.r + (s.t + (A + B * 2) / 6) * dt, s.t + (A + B * 4 + C) / 6};
  }
}

// Sharma's stages from `d0` = D(s.r).
GrinState SharmaStages(const IndexField& f, const Vec3& c, const GrinState& s, const Vec3& d0,
                       double dt, double* err) {
  auto d_at = [&](const Vec3& r) { return D(f, c, r); };
  const Vec3 A = d0 * dt;
  const Vec3 B = d_at(s.r + s.t * (dt / 2) + A * (dt / 8)) * dt;
  return SharmaFinish(d_at, s, A, B, dt, err);
}

// The embedded estimate is of third order (error ~ dt^4): the factor for the next step is the
// fourth root of tolerance / err (x 0.9, within [0.2, 4]; below tolerance / 400 it is 4 without
// roots, as 0.9 * 400^(1/4) > 4). A step that was `limited` below the proposal *dt (by a cell
// face) and had error to spare (the factor would be >= 1) leaves the proposal standing.
double Proposal(double err, double tolerance, double h, bool limited, double dt) {
  if (limited && err * 1.6 <= tolerance) return std::max(dt, h);
  return h * (err * 400 <= tolerance
                  ? 4.0
                  : std::clamp(0.9 * std::sqrt(std::sqrt(tolerance / err)), 0.2, 4.0));
}

double Shrink(double err, double tolerance) {
  return std::clamp(0.9 * std::sqrt(std::sqrt(tolerance / err)), 0.1, 0.5);
}

}  // namespace

GrinState SharmaStep(const IndexField& f, const Vec3& c, const GrinState& s, double dt) {
  return SharmaStages(f, c, s, D(f, c, s.r), dt, nullptr);
}

namespace {

// The former controller: step doubling of Sharma steps (three steps per try).
int StepDoubling(const IndexField& f, const Vec3& c, const GrinSettings& cfg, double cap,
                 GrinState* s, double* dt, double* used) {
  int evals = 0;
  for (int tries = 0;; ++tries) {
    double n = f.Index(s->r - c);
    ++evals;
    if (cap > 0) *dt = std::min(*dt, cap / n);  // ds = n dt
    const GrinState full = SharmaStep(f, c, *s, *dt);
    const GrinState half = SharmaStep(f, c, SharmaStep(f, c, *s, *dt / 2), *dt / 2);
    evals += 9;
    const double err = Length(full.r - half.r);
    if (err <= cfg.tolerance_um || tries > 60) {
      *s = half;
      *used = *dt;
      // Keep |T| = n(R): renormalise the optical direction to the local index.
      const double nn = f.Index(s->r - c);
      const double tl = Length(s->t);
      if (tl > 0) s->t = s->t * (nn / tl);
      const double grow = err > 0 ? 0.9 * std::pow(cfg.tolerance_um / err, 0.2) : 4.0;
      *dt *= std::clamp(grow, 0.2, 4.0);
      return evals + 1;
    }
    *dt *= std::clamp(0.9 * std::pow(cfg.tolerance_um / err, 0.2), 0.1, 0.5);
  }
}

double StepCap(const IndexField& f, const GrinSettings& cfg) {
  return cfg.max_step_um > 0 ? cfg.max_step_um : f.MaxStepUm();
}

// Cell steps end on faces; their cap (a cell's diagonal) only bounds a ray that turns inside one.
// Squared (um^2), so that the step compares (n dt)^2 with it and takes no root or division.
double CellStepCap2(const IndexField& f, const GrinSettings& cfg) {
  if (cfg.max_step_um > 0) return cfg.max_step_um * cfg.max_step_um;
  auto axis = [](int count, double h) { return count > 1 ? h * h : 0.0; };
  const double diagonal2 =
      axis(f.nx, f.spacing_um.x) + axis(f.ny, f.spacing_um.y) + axis(f.nz, f.spacing_um.z);
  return diagonal2 > 0 ? diagonal2 : std::numeric_limits<double>::infinity();  // one cell only
}

}  // namespace

GrinPoint MakeGrinPoint(const IndexField& f, const Vec3& c, const Vec3& r, const Vec3& t) {
  GrinPoint p;
  p.r = r;
  Vec3 g;
  f.Eval(r - c, &p.n, &g);
  p.d = g * p.n;
  const double tl = Length(t);
  p.t = tl > 0 ? t * (p.n / tl) : t;
  return p;
}

GrinPoint SharmaStep(const IndexField& f, const Vec3& c, const GrinPoint& s, double dt,
                     double* err) {
  const GrinState next = SharmaStages(f, c, GrinState{s.r, s.t}, s.d, dt, err);
  return MakeGrinPoint(f, c, next.r, next.t);
}

int AdaptiveStep(const IndexField& f, const Vec3& c, const GrinSettings& cfg, GrinPoint* s,
                 double* dt, double* used) {
  const double cap = StepCap(f, cfg);
  if (cfg.step_doubling) {
    GrinState st{s->r, s->t};
    const int evals = StepDoubling(f, c, cfg, cap, &st, dt, used);
    *s = MakeGrinPoint(f, c, st.r, st.t);
    return evals + 1;
  }
  if (cap > 0) *dt = std::min(*dt, cap / s->n);  // ds = n dt
  for (int tries = 0;; ++tries) {
    double err = 0;
    const GrinPoint next = SharmaStep(f, c, *s, *dt, &err);
    if (err <= cfg.tolerance_um || tries > 60) {
      *s = next;
      *used = *dt;
      *dt = Proposal(err, cfg.tolerance_um, *dt, false, *dt);
      return 3 * (tries + 1);
    }
    *dt *= Shrink(err, cfg.tolerance_um);
  }
}

int CellStep(const IndexField& f, const Vec3& c, const GrinSettings& cfg, GridCellPair* cells,
             GrinPoint* s, double* dt, double* used) {
  // A step that ends on a face lands kCellOvershoot past it; one that crosses a face by more than
  // kStraddle (the prediction missed it) is taken again, aimed at that face.
  constexpr double kStraddle = 1e-6;
  const Vec3 p = s->r - c;
  GridCell* cell = &cells->cell[cells->current];
  GridCell* spare = &cells->cell[1 - cells->current];
  if (!(cell->at.x == p.x && cell->at.y == p.y && cell->at.z == p.z)) *cell = f.Cell(p);
  const GridCell& g = *cell;
  const Vec3 inv = g.inv_spacing;
  const Vec3 u0 = Mul(p - g.node, inv);
  const double cap2 = CellStepCap2(f, cfg);
  // The largest parameter step within the cap (ds = n dt), computed only where it binds.
  auto capped = [&](double h) { return h * h * (s->n * s->n) > cap2 ? std::sqrt(cap2) / s->n : h; };
  CellExit exit = PredictCellExit(g, p, s->t, s->d);
  double h = capped(std::min(*dt, exit.dt));
  bool aim = h == exit.dt;
  // The cell beyond the face aimed at, prepared alongside the step (it needs only the face).
  const CellExit aimed = aim ? exit : CellExit();
  if (aim) f.NextCell(g, exit.axis, exit.side, spare);
  bool landed = false;  // the step ends kCellOvershoot past that face and crossed no other
  // All stages from the start cell's polynomial: the field the step sees is smooth.
  auto d_at = [&](const Vec3& r) {
    double n;
    Vec3 grad;
    IndexField::EvalInCell(g, r - c, &n, &grad);
    return grad * n;
  };
  GrinState next;
  double err = 0;
  int tries = 0;
  for (;; ++tries) {
    const Vec3 A = s->d * h;
    const Vec3 d_mid = d_at(s->r + s->t * (h / 2) + A * (h / 8)), B = d_mid * h;
    next = SharmaFinish<true>(d_at, GrinState{s->r, s->t}, A, B, h, &err);
    if (tries > 60) break;
    if (err > cfg.tolerance_um) {
      h *= Shrink(err, cfg.tolerance_um);
      aim = false;
      continue;
    }
    Vec3 u1 = Mul(next.r - c - g.node, inv);
    if (aim) {
      // The prediction (from D at the start only) misses the face by O(dD/dt dt^3): the step is
      // extended (or shortened) along the path onto it, kCellOvershoot past, by
      // r += T snap + D snap^2 / 2, T += D snap, with T and D at the end from the first two
      // stages (so that this runs alongside the last): T + B is T there to O(the step's error
      // / dt) and 2 D_mid - D0 is D there to O(d^2D/dt^2 dt^2). As the correction is ~1e-4 of
      // the step, the errors it adds are ~1e-4 of the step's own.
      const int a = exit.axis;
      const double target = (exit.side > 0 ? g.hi[a] : g.lo[a]) + exit.side * kCellOvershoot;
      const Vec3 t_end = s->t + B, d_end = d_mid * 2 - s->d;
      const double rvel = 1 / (t_end[a] * inv[a]), gap = target - u1[a];
      double snap = gap * rvel;
      snap = (gap - d_end[a] * inv[a] * snap * snap / 2) * rvel;
      if (std::abs(snap) < 0.01 * h) {
        next.r = next.r + t_end * snap + d_end * (snap * snap / 2);
        next.t = next.t + d_end * snap;
        h += snap;
        u1 = Mul(next.r - c - g.node, inv);
        landed = exit.axis == aimed.axis && exit.side == aimed.side;
      }
    }
    // A face the step crossed by more than kStraddle (the prediction missed it: another face
    // first, or a snap too long): the step is taken again, aimed at the first such face.
    double first = 1;
    CellExit missed;
    for (int a = 0; a < 3; ++a) {
      const double side = u1[a] > g.hi[a] + kStraddle   ? 1.0
                          : u1[a] < g.lo[a] - kStraddle ? -1.0
                                                        : 0.0;
      if (side == 0) continue;
      const double face = side > 0 ? g.hi[a] : g.lo[a];
      const double along = (face - u0[a]) / (u1[a] - u0[a]);  // chord fraction at the face
      if (along < first) first = along, missed = {h * along, a, int(side)};
    }
    if (missed.axis < 0) break;
    landed = false;
    exit = missed;
    h = std::max(exit.dt, 1e-3 * h);
    aim = true;
  }
  *used = h;
  *dt = capped(Proposal(err, cfg.tolerance_um, h, aim, *dt));
  // The end point in its own cell, which the next step starts from (the gradient jumps at the
  // face: the next step's first stage is the next cell's).
  const Vec3 q = next.r - c;
  if (landed) {
    cells->current = 1 - cells->current;
    cell = spare;
  } else {
    *cell = f.CellWith(q, inv);
  }
  cell->at = q;
  Vec3 grad;
  s->r = next.r;
  IndexField::EvalInCell(*cell, q, &s->n, &grad);
  s->d = grad * s->n;
  // Keep |T| = n(R), as MakeGrinPoint does (skipping it where |T| had not drifted saved
  // nothing measurable).
  const double t2 = Dot(next.t, next.t);
  s->t = t2 > 0 ? next.t * (s->n / std::sqrt(t2)) : next.t;
  return 3 * (tries + 1);
}

int AdaptiveStep(const IndexField& f, const Vec3& c, const GrinSettings& cfg, GrinState* s,
                 double* dt, double* used) {
  GrinPoint p = MakeGrinPoint(f, c, s->r, s->t);
  const int evals = AdaptiveStep(f, c, cfg, &p, dt, used);
  s->r = p.r, s->t = p.t;
  return evals + 1;
}

// ---- Uniform cells ----------------------------------------------------------------------

UniformCells::UniformCells(const IndexField& f, double tolerance, int block) {
  if (tolerance < 0) return;
  if (f.type == IndexFieldType::kGrid3D) {
    cx_ = f.nx - 1, cy_ = f.ny - 1, cz_ = f.nz - 1;
  } else if (f.type == IndexFieldType::kGridRZ) {
    rz_ = true;
    cx_ = f.nx - 1, cy_ = 1, cz_ = f.nz - 1;
  } else {
    return;
  }
  if (cx_ < 1 || cy_ < 1 || cz_ < 1) return;
  rotated_ = f.rotated, rotation_t_ = f.rotation_t;
  origin_ = f.origin_um, spacing_ = f.spacing_um;
  inv_spacing_ = {1 / spacing_.x, 1 / spacing_.y, 1 / spacing_.z};
  dist_.assign(size_t(cx_) * cy_ * cz_, 0);
  auto node = [&](int k, int j, int i) {
    return rz_ ? f.values[size_t(k) * f.nx + i] : f.values[(size_t(k) * f.ny + j) * f.nx + i];
  };
  auto at = [&](int k, int j, int i) -> uint8_t& { return dist_[(size_t(k) * cy_ + j) * cx_ + i]; };
  const int dj = rz_ ? 0 : 1;
  for (int k = 0; k < cz_; ++k)
    for (int j = 0; j < cy_; ++j)
      for (int i = 0; i < cx_; ++i) {
        double lo = node(k, j, i), hi = lo;
        for (int a = 0; a < 2; ++a)
          for (int b = 0; b <= dj; ++b)
            for (int e = 0; e < 2; ++e) {
              const double v = node(k + a, j + b, i + e);
              lo = std::min(lo, v), hi = std::max(hi, v);
            }
        at(k, j, i) = hi - lo <= tolerance ? 255 : 0;
      }
  // Blocks of B^3 cells (B^2 in r-z): uniform when all their cells are. A block at the grid's
  // edge may reach past it, where the field holds its edge values: the same constant. B is the
  // smallest of 1, 2, 4 whose map has at most kMaxBlocks entries, so that looking it up at
  // every step stays in the processor's cache (a per-cell map is slower on a 96^3 grid, bench/),
  // while a small grid's straight steps reach its cells' own boundaries (which is faster than
  // stopping at block boundaries when the whole map fits the cache).
  {
    const size_t cells_all = size_t(cx_) * cy_ * cz_;
    block_ = block > 0 ? block : 1;
    while (block <= 0 && block_ < 4 &&
           cells_all / (size_t(block_) * block_ * (rz_ ? 1 : block_)) > kMaxBlocks)
      block_ *= 2;
    const int bx = (cx_ + block_ - 1) / block_, by = rz_ ? 1 : (cy_ + block_ - 1) / block_,
              bz = (cz_ + block_ - 1) / block_;
    const int sy = rz_ ? 1 : block_;
    std::vector<uint8_t> blocks(size_t(bx) * by * bz, 0);
    for (int K = 0; K < bz; ++K)
      for (int J = 0; J < by; ++J)
        for (int I = 0; I < bx; ++I) {
          bool ok = true;
          size_t cells = 0;
          for (int k = K * block_; ok && k < std::min(cz_, (K + 1) * block_); ++k)
            for (int j = J * sy; ok && j < std::min(cy_, (J + 1) * sy); ++j)
              for (int i = I * block_; ok && i < std::min(cx_, (I + 1) * block_); ++i, ++cells)
                ok = at(k, j, i) != 0;
          blocks[(size_t(K) * by + J) * bx + I] = ok ? 255 : 0;
          if (ok) uniform_cells_ += cells;
        }
    dist_ = std::move(blocks);
    cx_ = bx, cy_ = by, cz_ = bz;
    spacing_ = {spacing_.x * block_, spacing_.y * sy, spacing_.z * block_};
    inv_spacing_ = {1 / spacing_.x, 1 / spacing_.y, 1 / spacing_.z};
  }
  // An axisymmetric grid that starts on the axis continues through it (r >= 0 mirrors): the
  // block at r index -1 is block 0. Other edges count as non-uniform (the field beyond them is
  // extrapolated, not sampled).
  const bool mirror_r = rz_ && f.origin_um.x <= 0;
  auto neighbour = [&](int k, int j, int i) -> int {
    if (rz_ && j != 0) return -1;  // no such neighbour (no y axis)
    if (i < 0 && mirror_r) i = -1 - i;
    if (k < 0 || k >= cz_ || j < 0 || j >= cy_ || i < 0 || i >= cx_) return 0;
    return at(k, j, i);
  };
  // Two-pass chamfer transform with the 26-neighbourhood: exact for the Chebyshev distance.
  auto pass = [&](int k, int j, int i, int sgn) {
    uint8_t& d = at(k, j, i);
    if (d == 0) return;
    int m = d;
    for (int a = -1; a <= 1; ++a)
      for (int b = -1; b <= 1; ++b)
        for (int e = -1; e <= 1; ++e) {
          // Neighbours already visited in this pass's order.
          const int order = a != 0 ? a : (b != 0 ? b : e);
          if (order * sgn >= 0) continue;
          const int v = neighbour(k + a, j + b, i + e);
          if (v >= 0) m = std::min(m, v + 1);
        }
    d = static_cast<uint8_t>(std::min(m, 255));
  };
  for (int k = 0; k < cz_; ++k)
    for (int j = 0; j < cy_; ++j)
      for (int i = 0; i < cx_; ++i) pass(k, j, i, 1);
  for (int k = cz_ - 1; k >= 0; --k)
    for (int j = cy_ - 1; j >= 0; --j)
      for (int i = cx_ - 1; i >= 0; --i) pass(k, j, i, -1);
}

double UniformCells::FreeLength(const Vec3& local) const {
  if (dist_.empty()) return 0;
  // (A rotated field's blocks are in its own axes; lengths do not change under the rotation.)
  const Vec3 p = rotated_ ? rotation_t_ * local : local;
  // Cell coordinates along each used axis (r, z for axisymmetric grids).
  const double ux = ((rz_ ? std::sqrt(p.x * p.x + p.y * p.y) : p.x) - origin_.x) * inv_spacing_.x;
  const double uy = rz_ ? 0.5 : (p.y - origin_.y) * inv_spacing_.y;
  const double uz = (p.z - origin_.z) * inv_spacing_.z;
  if (!(ux >= 0 && ux < cx_ && uy >= 0 && uy < cy_ && uz >= 0 && uz < cz_)) return 0;  // blocks
  const int i = static_cast<int>(ux), j = static_cast<int>(uy), k = static_cast<int>(uz);
  const int d = dist_[(size_t(k) * cy_ + j) * cx_ + i];
  if (d == 0) return 0;
  // Every block within Chebyshev distance d - 1 of this one is uniform: a straight path may go
  // as far as the nearest face of that block along any axis.
  auto room = [&](double u, int c) { return std::min(u - (c - (d - 1)), c + d - u); };
  double len = std::min(room(ux, i) * spacing_.x, room(uz, k) * spacing_.z);
  if (!rz_) len = std::min(len, room(uy, j) * spacing_.y);
  return std::max(0.0, len);
}

}  // namespace raymatch::simulate
