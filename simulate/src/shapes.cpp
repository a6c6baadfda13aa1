#include "raymatch/simulate/shapes.h"

#include <embree3/rtcore.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "raymatch/core/error.h"

namespace raymatch::simulate {

TriangleMesh RevolveOutline(const Outline& in, int segments) {
  if (in.size() < 2) throw Error("an outline needs at least two (r, z) points");
  if (segments < 8) throw Error("a surface of revolution needs at least 8 segments");
  for (const auto& p : in)
    if (!(std::isfinite(p[0]) && std::isfinite(p[1])) || p[0] < 0)
      throw Error("outline points must be finite with r >= 0");
  Outline o = in;
  // Close the ends on the axis (flat caps when an end is off the axis).
  if (o.front()[0] > 0) o.insert(o.begin(), {0.0, o.front()[1]});
  if (o.back()[0] > 0) o.push_back({0.0, o.back()[1]});
  TriangleMesh m;
  // Ring k: one vertex if r == 0 (a pole), else `segments` vertices.
  std::vector<unsigned> first(o.size());
  for (size_t k = 0; k < o.size(); ++k) {
    first[k] = static_cast<unsigned>(m.vertices.size());
    const double r = o[k][0], z = o[k][1];
    if (r == 0) {
      m.vertices.push_back({0, 0, z});
      continue;
    }
    for (int j = 0; j < segments; ++j) {
      const double a = 2 * M_PI * j / segments;
      m.vertices.push_back({r * std::cos(a), r * std::sin(a), z});
    }
  }
  auto idx = [&](size_t k, int j) {
    return o[k][0] == 0 ? first[k] : first[k] + static_cast<unsigned>(j % segments);
  };
  for (size_t k = 0; k + 1 < o.size(); ++k) {
    const bool pole_a = o[k][0] == 0, pole_b = o[k + 1][0] == 0;
    if (pole_a && pole_b) continue;
    for (int j = 0; j < segments; ++j) {
      const unsigned a0 = idx(k, j), a1 = idx(k, j + 1), b0 = idx(k + 1, j), b1 = idx(k + 1, j + 1);
      if (pole_a) {
        m.triangles.push_back({a0, b0, b1});
      } else if (pole_b) {
        m.triangles.push_back({a0, b0, a1});
      } else {
        m.triangles.push_back({a0, b0, b1});
        m.triangles.push_back({a0, b1, a1});
      }
    }
  }
  return m;
}

Outline OutlineFromSilhouette(const Image& image, const SilhouetteOptions& opt,
                              double* fitted_axis) {
  if (image.empty()) throw Error("silhouette image is empty");
  cv::Mat img(image.height, image.width, CV_32F, const_cast<float*>(image.pixels.data()));
  if (!opt.vertical_axis) img = img.t();  // work with the axis along rows of `img`' columns
  std::vector<float> sorted(img.begin<float>(), img.end<float>());
  std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
  const double bg = sorted[sorted.size() / 2];
  double lo, hi;
  cv::minMaxLoc(img, &lo, &hi);
  if (!(bg > lo)) throw Error("silhouette image has no object darker than its background");
  cv::Mat mask = img < (lo + opt.threshold * (bg - lo));
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(mask, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
  if (contours.empty()) throw Error("no silhouette found (check threshold)");
  size_t best = 0;
  for (size_t i = 1; i < contours.size(); ++i)
    if (cv::contourArea(contours[i]) > cv::contourArea(contours[best])) best = i;
  cv::Mat filled = cv::Mat::zeros(img.size(), CV_8U);
  cv::drawContours(filled, contours, static_cast<int>(best), 255, cv::FILLED);
  // Per row across the axis (image rows when the axis is vertical): the blob's extent.
  std::vector<double> left(img.rows, -1), right(img.rows, -1);
  double axis_sum = 0, axis_w = 0;
  for (int y = 0; y < img.rows; ++y) {
    const uchar* row = filled.ptr<uchar>(y);
    int a = -1, b = -1;
    for (int x = 0; x < img.cols; ++x)
      if (row[x]) {
        if (a < 0) a = x;
        b = x;
      }
    if (a < 0) continue;
    left[y] = a, right[y] = b + 1;  // pixel edges
    const double w = b + 1 - a;
    axis_sum += w * 0.5 * (a + b + 1), axis_w += w;
  }
  if (axis_w == 0) throw Error("silhouette is empty after filling");
  const double axis = opt.axis_px >= 0 ? opt.axis_px : axis_sum / axis_w;
  if (fitted_axis) *fitted_axis = axis;
  int y0 = 0, y1 = img.rows - 1;
  while (left[y0] < 0) ++y0;
  while (left[y1] < 0) --y1;
  std::vector<double> r(y1 - y0 + 1);
  for (int y = y0; y <= y1; ++y)
    r[y - y0] =
        left[y] < 0 ? 0 : 0.5 * (std::max(0.0, axis - left[y]) + std::max(0.0, right[y] - axis));
  if (opt.smooth_px > 0) {
    cv::Mat rv(1, static_cast<int>(r.size()), CV_64F, r.data()), sm;
    cv::GaussianBlur(rv, sm, cv::Size(0, 0), opt.smooth_px, 0, cv::BORDER_REPLICATE);
    for (size_t i = 0; i < r.size(); ++i) r[i] = sm.at<double>(0, static_cast<int>(i));
  }
  // z up = towards row 0; centred on the blob. Poles half a pixel beyond the first/last rows.
  const double zc = 0.5 * (y0 + y1 + 1);
  Outline out;
  out.push_back({0.0, (zc - y1 - 1) * opt.pixel_um});
  for (int y = y1; y >= y0; --y)
    out.push_back({r[y - y0] * opt.pixel_um, (zc - y - 0.5) * opt.pixel_um});
  out.push_back({0.0, (zc - y0) * opt.pixel_um});
  return out;
}

Outline ReadOutlineCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(FileLocation{path}, "cannot open outline file");
  Outline o;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#') continue;
    std::replace(line.begin(), line.end(), ',', ' ');
    std::istringstream ss(line);
    double r, z;
    if (!(ss >> r >> z)) {
      if (o.empty() && n == 1) continue;  // header
      throw Error(FileLocation{path, n, 1}, "expected two numbers 'r_um,z_um'");
    }
    if (r < 0) throw Error(FileLocation{path, n, 1}, "radius must be >= 0");
    o.push_back({r, z});
  }
  if (o.size() < 2) throw Error(FileLocation{path}, "an outline needs at least two points");
  return o;
}

std::string MeshReport::Summary() const {
  std::ostringstream s;
  s << triangles << " triangles";
  if (degenerate_removed) s << ", " << degenerate_removed << " degenerate removed";
  if (open_edges) s << ", " << open_edges << " open edges (not watertight)";
  if (nonmanifold_edges) s << ", " << nonmanifold_edges << " edges shared by >2 triangles";
  if (self_intersections) s << ", " << self_intersections << " self-intersections";
  if (flipped) s << ", winding reversed to outward";
  return s.str();
}

MeshReport CheckAndOrientMesh(TriangleMesh* mesh) {
  MeshReport rep;
  auto& V = mesh->vertices;
  auto& T = mesh->triangles;
  double scale = 0;
  for (const Vec3& v : V) scale = std::max({scale, std::abs(v.x), std::abs(v.y), std::abs(v.z)});
  const double min_area = 1e-14 * std::max(scale * scale, 1e-30);
  // Triangles with a repeated vertex are dropped. Zero-area triangles with distinct vertices are
  // dropped only when dangling (an edge no other triangle uses); slivers inside a surface, as
  // iso-surfacers emit, stay: removing them would open the topology.
  auto key = [](unsigned a, unsigned b) { return std::make_pair(std::min(a, b), std::max(a, b)); };
  std::vector<std::array<unsigned, 3>> kept;
  std::map<std::pair<unsigned, unsigned>, int> use;
  for (const auto& t : T) {
    if (t[0] == t[1] || t[1] == t[2] || t[0] == t[2]) {
      ++rep.degenerate_removed;
      continue;
    }
    kept.push_back(t);
    for (int e = 0; e < 3; ++e) use[key(t[e], t[(e + 1) % 3])]++;
  }
  T.clear();
  for (const auto& t : kept) {
    const double area = 0.5 * Length(Cross(V[t[1]] - V[t[0]], V[t[2]] - V[t[0]]));
    bool dangling = false;
    for (int e = 0; e < 3; ++e) dangling |= use[key(t[e], t[(e + 1) % 3])] == 1;
    if (!(area > min_area) && dangling) {
      ++rep.degenerate_removed;
      for (int e = 0; e < 3; ++e) use[key(t[e], t[(e + 1) % 3])]--;
      continue;
    }
    T.push_back(t);
  }
  rep.triangles = T.size();
  // Edges: count each undirected edge; a closed, consistently wound surface uses each exactly
  // twice, once in each direction.
  std::map<std::pair<unsigned, unsigned>, int> edges;
  for (const auto& t : T)
    for (int e = 0; e < 3; ++e) {
      const unsigned a = t[e], b = t[(e + 1) % 3];
      edges[{std::min(a, b), std::max(a, b)}]++;
    }
  for (const auto& [e, c] : edges) {
    if (c == 1) ++rep.open_edges;
    if (c > 2) ++rep.nonmanifold_edges;
  }
  double vol = 0;
  for (const auto& t : T) vol += Dot(V[t[0]], Cross(V[t[1]], V[t[2]])) / 6.0;
  rep.signed_volume_um3 = vol;
  if (vol < 0) {
    for (auto& t : T) std::swap(t[1], t[2]);
    rep.flipped = true;
    rep.signed_volume_um3 = -vol;
  }
  // Self-intersection: every edge as a segment against all triangles that do not share its
  // end points.
  if (!T.empty()) {
    RTCDevice dev = rtcNewDevice(nullptr);
    RTCScene sc = rtcNewScene(dev);
    RTCGeometry g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
    float* vb = static_cast<float*>(rtcSetNewGeometryBuffer(
        g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), V.size()));
    for (size_t i = 0; i < V.size(); ++i)
      vb[3 * i] = float(V[i].x), vb[3 * i + 1] = float(V[i].y), vb[3 * i + 2] = float(V[i].z);
    unsigned* ib = static_cast<unsigned*>(rtcSetNewGeometryBuffer(
        g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(unsigned), T.size()));
    for (size_t i = 0; i < T.size(); ++i) std::copy(T[i].begin(), T[i].end(), ib + 3 * i);
    rtcCommitGeometry(g);
    rtcAttachGeometry(sc, g);
    rtcReleaseGeometry(g);
    rtcCommitScene(sc);
    for (const auto& [e, c] : edges) {
      const Vec3 a = V[e.first], b = V[e.second];
      const double len = Length(b - a);
      if (!(len > 0)) continue;
      const Vec3 d = (b - a) / len;
      RTCIntersectContext ctx;
      rtcInitIntersectContext(&ctx);
      RTCRayHit rh;
      rh.ray.org_x = float(a.x), rh.ray.org_y = float(a.y), rh.ray.org_z = float(a.z);
      rh.ray.dir_x = float(d.x), rh.ray.dir_y = float(d.y), rh.ray.dir_z = float(d.z);
      rh.ray.tnear = float(1e-4 * len);
      rh.ray.tfar = float((1 - 1e-4) * len);
      rh.ray.mask = 0xFFFFFFFFu, rh.ray.flags = 0, rh.ray.time = 0;
      rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
      rtcIntersect1(sc, &ctx, &rh);
      if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) continue;
      const auto& t = T[rh.hit.primID];
      const bool shares =
          std::count(t.begin(), t.end(), e.first) || std::count(t.begin(), t.end(), e.second);
      if (!shares) ++rep.self_intersections;
    }
    rtcReleaseScene(sc);
    rtcReleaseDevice(dev);
  }
  return rep;
}

}  // namespace raymatch::simulate
