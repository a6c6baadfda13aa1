#include "raymatch/simulate/index_field.h"

#include <algorithm>
#include <cmath>

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

void IndexField::Eval(const Vec3& p, double* n, Vec3* grad) const {
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
      auto v = [&](int a, int b) {  // a: z index, b: r index
        return values[size_t(std::min(a, nz - 1)) * nx + std::min(b, nx - 1)];
      };
      const double v00 = v(iz, ir), v01 = v(iz, ir + 1), v10 = v(iz + 1, ir),
                   v11 = v(iz + 1, ir + 1);
      const double a0 = v00 + (v01 - v00) * fr, a1 = v10 + (v11 - v10) * fr;
      *n = a0 + (a1 - a0) * fz;
      const double dn_dr =
          in_r ? ((v01 - v00) * (1 - fz) + (v11 - v10) * fz) / spacing_um.x : 0.0;
      const double dn_dz = in_z ? (a1 - a0) / spacing_um.z : 0.0;
      // On the axis dn/dr is taken as 0 (the field is smooth and symmetric there).
      const Vec3 radial = r > 1e-12 ? Vec3(p.x / r, p.y / r, 0) : Vec3();
      *grad = radial * dn_dr + Vec3(0, 0, dn_dz);
      return;
    }
    case IndexFieldType::kGrid3D: {
      // The 8 corners addressed from one base index; an axis with a single sample has stride 0
      // (its "next" corner is itself), and Locate keeps every other index at most n - 2.
      int ix, iy, iz;
      double fx, fy, fz;
      bool inx, iny, inz;
      Locate((p.x - origin_um.x) / spacing_um.x, nx, &ix, &fx, &inx);
      Locate((p.y - origin_um.y) / spacing_um.y, ny, &iy, &fy, &iny);
      Locate((p.z - origin_um.z) / spacing_um.z, nz, &iz, &fz, &inz);
      const size_t sx = nx > 1 ? 1 : 0, sy = ny > 1 ? size_t(nx) : 0,
                   sz = nz > 1 ? size_t(nx) * size_t(ny) : 0;
      const double* b =
          values.data() + ((size_t(iz) * size_t(ny) + size_t(iy)) * size_t(nx) + size_t(ix));
      auto lerp = [](double a, double c, double t) { return a + (c - a) * t; };
      const double c00 = lerp(b[0], b[sx], fx), c01 = lerp(b[sy], b[sy + sx], fx);
      const double c10 = lerp(b[sz], b[sz + sx], fx), c11 = lerp(b[sz + sy], b[sz + sy + sx], fx);
      const double d00 = b[sx] - b[0], d01 = b[sy + sx] - b[sy];
      const double d10 = b[sz + sx] - b[sz], d11 = b[sz + sy + sx] - b[sz + sy];
      const double cy0 = lerp(c00, c01, fy), cy1 = lerp(c10, c11, fy);
      *n = lerp(cy0, cy1, fz);
      const double gx = lerp(lerp(d00, d01, fy), lerp(d10, d11, fy), fz);
      const double gy = lerp(c01 - c00, c11 - c10, fz);
      const double gz = cy1 - cy0;
      *grad = Vec3(inx ? gx / spacing_um.x : 0, iny ? gy / spacing_um.y : 0,
                   inz ? gz / spacing_um.z : 0);
      return;
    }
  }
}

double IndexField::MaxStepUm() const {
  switch (type) {
    case IndexFieldType::kGridRZ: return 0.5 * std::min(spacing_um.x, spacing_um.z);
    case IndexFieldType::kGrid3D:
      return 0.5 * std::min({spacing_um.x, spacing_um.y, spacing_um.z});
    default: return 0;
  }
}

namespace {

// D = n grad n = grad(n^2) / 2 at world point r.
Vec3 D(const IndexField& f, const Vec3& c, const Vec3& r) {
  double n;
  Vec3 g;
  f.Eval(r - c, &n, &g);
  return g * n;
}

// Sharma's stages from `d0` = D(s.r): the state after dt and (optional) the embedded estimate.
GrinState SharmaStages(const IndexField& f, const Vec3& c, const GrinState& s, const Vec3& d0,
                       double dt, double* err) {
  const Vec3 A = d0 * dt;
  const Vec3 B = D(f, c, s.r + s.t * (dt / 2) + A * (dt / 8)) * dt;
  const Vec3 C = D(f, c, s.r + s.t * dt + B * (dt / 2)) * dt;
  if (err) *err = Length(A - B * 2 + C) * (std::abs(dt) / 6);
  return {s.r + (s.t + (A + B * 2) / 6) * dt, s.t + (A + B * 4 + C) / 6};
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
      // The estimate is of third order (error ~ dt^4): the fourth root of the ratio.
      const double grow = err > 0 ? 0.9 * std::sqrt(std::sqrt(cfg.tolerance_um / err)) : 4.0;
      *dt *= std::clamp(grow, 0.2, 4.0);
      return 3 * (tries + 1);
    }
    *dt *= std::clamp(0.9 * std::sqrt(std::sqrt(cfg.tolerance_um / err)), 0.1, 0.5);
  }
}

int AdaptiveStep(const IndexField& f, const Vec3& c, const GrinSettings& cfg, GrinState* s,
                 double* dt, double* used) {
  GrinPoint p = MakeGrinPoint(f, c, s->r, s->t);
  const int evals = AdaptiveStep(f, c, cfg, &p, dt, used);
  s->r = p.r, s->t = p.t;
  return evals + 1;
}

// ---- Uniform cells ----------------------------------------------------------------------

UniformCells::UniformCells(const IndexField& f, double tolerance) {
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
  // Blocks of kBlock^3 cells (kBlock^2 in r-z): uniform when all their cells are. A block at
  // the grid's edge may reach past it, where the field holds its edge values: the same
  // constant. The map of blocks is 1/64 of the grid's cell count, so looking it up at every
  // step stays in the processor's cache (a per-cell map cost 20 % on a 96^3 grid).
  {
    const int bx = (cx_ + kBlock - 1) / kBlock, by = rz_ ? 1 : (cy_ + kBlock - 1) / kBlock,
              bz = (cz_ + kBlock - 1) / kBlock;
    const int sy = rz_ ? 1 : kBlock;
    std::vector<uint8_t> blocks(size_t(bx) * by * bz, 0);
    for (int K = 0; K < bz; ++K)
      for (int J = 0; J < by; ++J)
        for (int I = 0; I < bx; ++I) {
          bool ok = true;
          size_t cells = 0;
          for (int k = K * kBlock; ok && k < std::min(cz_, (K + 1) * kBlock); ++k)
            for (int j = J * sy; ok && j < std::min(cy_, (J + 1) * sy); ++j)
              for (int i = I * kBlock; ok && i < std::min(cx_, (I + 1) * kBlock); ++i, ++cells)
                ok = at(k, j, i) != 0;
          blocks[(size_t(K) * by + J) * bx + I] = ok ? 255 : 0;
          if (ok) uniform_cells_ += cells;
        }
    dist_ = std::move(blocks);
    cx_ = bx, cy_ = by, cz_ = bz;
    spacing_ = {spacing_.x * kBlock, spacing_.y * sy, spacing_.z * kBlock};
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

double UniformCells::FreeLength(const Vec3& p) const {
  if (dist_.empty()) return 0;
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
