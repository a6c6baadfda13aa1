#include "image_model.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <thread>

#include "raymatch/core/error.h"
#include "raymatch/core/rng.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/wave_image.h"

namespace raymatch::fit::internal {

namespace {

/// Ray streams of the light field's part beyond the NA (a fit with the edge's keys): the plane
/// index plus this, independent of every plane's own streams.
constexpr uint32_t kBeyondStreams = 1u << 30;
/// Streams of the PSF draws of a fit with the PSF as a key (DrawPsf).
constexpr uint32_t kPsfStreams = 1u << 29;

/// The inverse normal CDF at the midpoints of kNormalBins equal-probability bins (NormalFromWord).
constexpr int kNormalBins = 1 << 14;
const std::vector<float>& NormalTable() {
  static const std::vector<float> table = [] {
    std::vector<float> t(kNormalBins);
    for (int k = 0; k < kNormalBins; ++k) {
      const double p = (k + 0.5) / kNormalBins;
      double lo = -10, hi = 10;
      for (int it = 0; it < 64; ++it) {
        const double mid = 0.5 * (lo + hi);
        (0.5 * std::erfc(-mid / std::sqrt(2.0)) < p ? lo : hi) = mid;
      }
      t[size_t(k)] = float(0.5 * (lo + hi));
    }
    return t;
  }();
  return table;
}

/// A standard normal deviate from one 32-bit word: NormalTable() interpolated linearly (tails
/// cut at 4.0 sd: the variance is 0.1 % short). Several times faster than Box-Muller, for the
/// PSF draws of every ray of a fit evaluation.
inline double NormalFromWord(const float* table, uint32_t w) {
  const double pos = w * (double(kNormalBins) * 0x1p-32) - 0.5;
  if (pos <= 0) return table[0];
  const int k = std::min(int(pos), kNormalBins - 2);
  const double f = std::min(pos - k, 1.0);
  return table[size_t(k)] + f * (table[size_t(k) + 1] - table[size_t(k)]);
}

}  // namespace

MieImageModel::~MieImageModel() = default;

ModelImages MieImageModel::Images(const simulate::Scene& scene, const Draw& draw, uint64_t*) {
  if (last_ && !draw.across_key.empty() && draw.across_key == last_key_) {
    // The kept fields serve a lateral move of the whole sphere; a key that moves a coated
    // sphere's shell or core alone is refused as a fresh imager would refuse it.
    if (const std::string why = simulate::MieUnsupportedReason(scene); !why.empty())
      throw Error(FileLocation{scene.file}, why);
    const Vec3& c = scene.objects.at(0).center_um;
    last_->MoveAcross(c.x, c.y);
  } else {
    // The exact wave image in photons at the experiment's flat-field count.
    simulate::Scene w = AtPhotonTarget(scene);
    if (w.trace.mie.window_um == 0) w.trace.mie.window_um = window_um_;
    last_ = std::make_unique<simulate::MieImager>(w);
    last_key_ = draw.across_key;
  }
  ModelImages out;
  for (double dz : scene.defocus_um) out.counts.push_back(last_->Expected(dz, threads_));
  return out;
}

ModelImages PhysicalImageModel::Images(const simulate::Scene& scene, const Draw&,
                                       uint64_t* rays_traced) {
  simulate::Scene w = AtPhotonTarget(scene);
  if (w.trace.physical.window_um == 0) w.trace.physical.window_um = window_um_;
  simulate::PhysicalImager imager(w);
  imager.KeepLayouts(layouts_);
  ModelImages out;
  for (double dz : scene.defocus_um) {
    out.counts.push_back(imager.Expected(dz, threads_));
    if (rays_traced) *rays_traced += imager.sampling().field_rays;
  }
  return out;
}

simulate::Scene TracedScene(simulate::Scene s, simulate::SourceSpec::EdgePart part, int psf_os,
                            int psf_margin) {
  s.source.edge_part = part;
  if (psf_os > 1) {
    s.camera.psf_sigma_um = 0;
    s.camera.nx = s.camera.nx * psf_os + 2 * psf_margin;
    s.camera.ny = s.camera.ny * psf_os + 2 * psf_margin;
    s.camera.pixel_pitch_um /= psf_os;
  }
  return s;
}

void RayImageModel::SetRegion(const Vec3& center, double radius) {
  setup_.region_center = center, setup_.region_radius = radius;
  near_.clear();
  background_.clear();
  psf_background_.clear();
}

std::shared_ptr<const Image> RayImageModel::BackgroundAt(const simulate::Simulator& sim, size_t i,
                                                         uint64_t seed, double dz, uint64_t n,
                                                         const simulate::RunControl& rc,
                                                         uint64_t* rays_traced) {
  const uint32_t plane = static_cast<uint32_t>(i);
  NearRays& near = near_[{i, seed}];
  auto it = background_.find({i, seed, dz});
  if (it != background_.end() && it->second.rays > n) return nullptr;  // cannot take rays away
  const auto t0 = std::chrono::steady_clock::now();
  if (it == background_.end()) {
    if (background_.size() >= 64) background_.erase(background_.begin());  // bounded memory
    it = background_.emplace(std::make_tuple(i, seed, dz), Background{}).first;
  }
  Background& bg = it->second;
  const uint64_t start = bg.rays;
  auto add = [&](const simulate::PlaneResult& r) {
    auto sum = bg.image ? std::make_shared<Image>(*bg.image)
                        : std::make_shared<Image>(r.counts.width, r.counts.height);
    for (size_t p = 0; p < r.counts.size(); ++p) sum->pixels[p] += r.counts.pixels[p];
    bg.image = std::move(sum);
  };
  // Rays whose near/far split is known (another defocus found it): trace the far ones.
  if (bg.rays < std::min(n, near.rays)) {
    const uint64_t to = std::min(n, near.rays);
    add(sim.TraceRangeExcept(dz, plane, bg.rays, to, near.list, rc));
    bg.rays = to;
  }
  // New rays: split and trace the far ones in one sampling pass.
  if (bg.rays < n) {
    RAYMATCH_CHECK(bg.rays == near.rays);
    add(sim.TraceFarRays(dz, plane, bg.rays, n, setup_.region_center, setup_.region_radius,
                         &near.list, rc));
    bg.rays = near.rays = n;
  }
  if (rays_traced && bg.rays > start) {
    const auto lo = std::lower_bound(near.list.begin(), near.list.end(), start);
    const auto hi = std::lower_bound(near.list.begin(), near.list.end(), bg.rays);
    *rays_traced += (bg.rays - start) - uint64_t(hi - lo);
  }
  background_seconds_ +=
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return bg.image;
}

Image DrawPsf(const Image& fine, int os, int margin, double sigma_fine, uint64_t seed,
              uint32_t plane, const Image* skip, int threads) {
  const int nx = (fine.width - 2 * margin) / os, ny = (fine.height - 2 * margin) / os;
  const int rows = fine.height;
  const float* const table = NormalTable().data();
  const int workers =
      std::max(1, std::min(threads > 0 ? threads : int(std::thread::hardware_concurrency()), rows));
  std::vector<Image> part(size_t(workers), Image(nx, ny));
  auto run = [&](int w) {
    Image& out = part[size_t(w)];
    for (int y = w; y < rows; y += workers)
      for (int x = 0; x < fine.width; ++x) {
        const size_t p = size_t(y) * fine.width + x;
        const uint64_t c = uint64_t(std::llround(fine.pixels[p]));
        const uint64_t first = skip ? uint64_t(std::llround(skip->pixels[p])) : 0;
        for (uint64_t j = first; j < c; ++j) {
          RayRng rng(seed, kPsfStreams + plane, (uint64_t(p) << 32) | j);  // one Philox block
          const double u0 = rng.Uniform(), u1 = rng.Uniform();
          const double gx = NormalFromWord(table, rng.NextU32()),
                       gy = NormalFromWord(table, rng.NextU32());
          const double fx = x + u0 + sigma_fine * gx - margin,
                       fy = y + u1 + sigma_fine * gy - margin;
          if (fx < 0 || fy < 0) continue;
          const int cx = int(fx) / os, cy = int(fy) / os;
          if (cx < nx && cy < ny) out.at(cx, cy) += 1.0f;
        }
      }
  };
  std::vector<std::thread> pool;
  for (int w = 1; w < workers; ++w) pool.emplace_back(run, w);
  run(0);
  for (std::thread& t : pool) t.join();
  for (int w = 1; w < workers; ++w)
    for (size_t p = 0; p < part[0].size(); ++p) part[0].pixels[p] += part[size_t(w)].pixels[p];
  return std::move(part[0]);
}

Image RayImageModel::ApplyPsf(const Image& fine, double sigma_um, uint64_t seed, uint32_t plane,
                              const Image* skip) const {
  const int os = setup_.psf_os;
  return DrawPsf(fine, os, setup_.psf_margin, sigma_um / (setup_.object_pixel_um / os), seed, plane,
                 skip, setup_.threads);
}

Image RayImageModel::PsfOf(const Image& fine, const std::shared_ptr<const Image>& background,
                           double sigma_um, uint64_t seed, uint32_t plane) {
  if (!background) return ApplyPsf(fine, sigma_um, seed, plane);
  const PsfBackground* kept = nullptr;
  for (const PsfBackground& k : psf_background_)
    if (k.background == background && k.sigma_um == sigma_um && k.seed == seed && k.plane == plane)
      kept = &k;
  if (!kept) {
    // Two images' backgrounds at a few sigmas: a derivative set's PSF steps come in between.
    constexpr size_t kKept = 8;
    if (psf_background_.size() >= kKept) psf_background_.erase(psf_background_.begin());
    psf_background_.push_back(
        {background, sigma_um, seed, plane, ApplyPsf(*background, sigma_um, seed, plane)});
    kept = &psf_background_.back();
  }
  Image out = ApplyPsf(fine, sigma_um, seed, plane, background.get());
  for (size_t p = 0; p < out.size(); ++p) out.pixels[p] += kept->image.pixels[p];
  return out;
}

const RayImageModel::Traced* RayImageModel::Recall(const std::vector<Traced>& kept,
                                                   const Traced& want) {
  if (want.key.empty()) return nullptr;
  for (const Traced& t : kept)
    if (t.seed == want.seed && t.rays == want.rays && t.key == want.key) return &t;
  return nullptr;
}

const RayImageModel::Traced* RayImageModel::Remember(std::vector<Traced>* kept, Traced t) {
  // A derivative set's centre and its steps share a key where a step moves only what the key
  // leaves out, and the steps of the other parameters come in between: enough for a set of
  // sixteen parameters (the counts of one evaluation's images each).
  constexpr size_t kKept = 16;
  if (kept->size() >= kKept) kept->erase(kept->begin());
  kept->push_back(std::move(t));
  return &kept->back();
}

RayImageModel::Traced RayImageModel::TraceInside(const simulate::Scene& full, const Traced& want,
                                                 uint64_t* rays_traced) {
  using Part = simulate::SourceSpec::EdgePart;
  Traced t = want;
  simulate::Scene scene = TracedScene(full, setup_.edge_split ? Part::kInside : Part::kAll,
                                      setup_.psf_os, setup_.psf_margin);
  scene.trace.seed = want.seed;
  const simulate::Simulator sim(scene);
  t.weight = sim.source_weight();
  const uint64_t n = want.rays;
  simulate::RunControl rc;
  rc.threads = setup_.threads;
  bool inside = setup_.split;
  if (inside)
    for (const auto& [c, r] : sim.ObjectBounds())
      inside = inside && Length(c - setup_.region_center) + r <= setup_.region_radius;
  for (size_t i = 0; i < setup_.images; ++i) {
    const double dz = scene.defocus_um[i];
    const uint32_t plane = static_cast<uint32_t>(i);
    std::shared_ptr<const Image> bg =
        inside ? BackgroundAt(sim, i, want.seed, dz, n, rc, rays_traced) : nullptr;
    t.background.push_back(bg);
    if (bg) {
      const std::vector<uint64_t>& near = near_.at({i, want.seed}).list;
      const auto end = std::lower_bound(near.begin(), near.end(), n);
      const std::span<const uint64_t> mine(near.data(), size_t(end - near.begin()));
      Image counts = sim.TraceRays(dz, plane, mine, rc).counts;
      for (size_t p = 0; p < counts.size(); ++p) counts.pixels[p] += bg->pixels[p];
      if (rays_traced) *rays_traced += mine.size();
      t.near_fraction = double(mine.size()) / double(n);
      t.counts.push_back(std::move(counts));
    } else {
      t.counts.push_back(sim.TracePlane(dz, plane, n, rc).counts);
      if (rays_traced) *rays_traced += n;
    }
  }
  return t;
}

RayImageModel::Traced RayImageModel::TraceBeyond(const simulate::Scene& full, const Traced& want,
                                                 double inside_weight,
                                                 uint64_t* rays_traced) const {
  // The rays beyond the NA: their own population and streams, in proportion to their weight,
  // traced whole. Their far rays are not kept as the inside part's are: those would be kept per
  // edge, and a fit's steps move the edge at almost every evaluation.
  Traced t = want;
  simulate::Scene b =
      TracedScene(full, simulate::SourceSpec::EdgePart::kBeyond, setup_.psf_os, setup_.psf_margin);
  b.trace.seed = want.seed;
  const simulate::Simulator beyond(b);
  t.weight = beyond.source_weight();
  const uint64_t rays = std::llround(double(want.rays) * t.weight / inside_weight);
  simulate::RunControl rc;
  rc.threads = setup_.threads;
  for (size_t i = 0; i < setup_.images && rays > 0; ++i) {
    const uint32_t plane = static_cast<uint32_t>(i) + kBeyondStreams;
    t.counts.push_back(beyond.TracePlane(b.defocus_um[i], plane, rays, rc).counts);
    if (rays_traced) *rays_traced += rays;
  }
  return t;
}

ModelImages RayImageModel::Images(const simulate::Scene& full, const Draw& draw,
                                  uint64_t* rays_traced) {
  // Each part is traced, or taken from an evaluation whose key says it traced the same rays
  // along the same paths (a derivative step of the edge or of the PSF): the same counts.
  Traced want_in;
  want_in.key = draw.inside_key, want_in.seed = draw.seed, want_in.rays = draw.rays;
  if (setup_.edge_split)
    want_in.rays = std::max<uint64_t>(1, std::llround(double(draw.rays) * setup_.inside_share));
  Traced fresh_in, fresh_out;
  const Traced* in = Recall(inside_, want_in);
  if (!in) {
    fresh_in = TraceInside(full, want_in, rays_traced);
    in = want_in.key.empty() ? &fresh_in : Remember(&inside_, std::move(fresh_in));
  }
  near_fraction_ = in->near_fraction;
  std::vector<Image> counts = in->counts;
  if (setup_.edge_split) {
    Traced want_out;
    want_out.key = draw.beyond_key, want_out.seed = draw.seed, want_out.rays = want_in.rays;
    const Traced* out = Recall(beyond_, want_out);
    if (!out) {
      fresh_out = TraceBeyond(full, want_out, in->weight, rays_traced);
      out = want_out.key.empty() ? &fresh_out : Remember(&beyond_, std::move(fresh_out));
    }
    for (size_t i = 0; i < out->counts.size(); ++i)
      for (size_t p = 0; p < counts[i].size(); ++p) counts[i].pixels[p] += out->counts[i].pixels[p];
  }
  ModelImages result;
  result.photons_per_count = draw.photons_per_ray;
  for (size_t i = 0; i < counts.size(); ++i)
    result.counts.push_back(setup_.psf_os > 1
                                ? PsfOf(counts[i], in->background.at(i), full.camera.psf_sigma_um,
                                        draw.seed, static_cast<uint32_t>(i))
                                : std::move(counts[i]));
  return result;
}

}  // namespace raymatch::fit::internal
