#include "raymatch/calibrate/mrcal_lightfield.h"

#include <algorithm>
#include <cmath>

#include "raymatch/core/error.h"

#if RAYMATCH_WITH_MRCAL
#include <Eigen/Geometry>
extern "C" {
#include <mrcal/mrcal.h>
}
#endif

namespace raymatch::calibrate {

#if RAYMATCH_WITH_MRCAL

bool MrcalAvailable() { return true; }

Image DirectionImageToAngularMap(const Image& ph, const std::string& path, int n, double extent,
                                 std::vector<char>* covered, DirectionMapStats* stats) {
  mrcal_cameramodel_t* model = mrcal_read_cameramodel_file(path.c_str());
  if (!model)
    throw Error(FileLocation{path},
                "mrcal could not read this .cameramodel (its parser printed the reason above)");
  struct Free {
    mrcal_cameramodel_t* m;
    ~Free() { mrcal_free_cameramodel(&m); }
  } free_model{model};
  if (int(model->imagersize[0]) != ph.width || int(model->imagersize[1]) != ph.height)
    throw Error(FileLocation{path},
                "the model's imager is " + std::to_string(model->imagersize[0]) + "x" +
                    std::to_string(model->imagersize[1]) + " but the image is " +
                    std::to_string(ph.width) + "x" + std::to_string(ph.height));
  // rt_cam_ref: p_cam = R p_ref + t; directions need only R (Rodrigues vector r).
  const Eigen::Vector3d r(model->rt_cam_ref[0], model->rt_cam_ref[1], model->rt_cam_ref[2]);
  const Eigen::Matrix3d R = r.norm() > 0
                                ? Eigen::AngleAxisd(r.norm(), r.normalized()).toRotationMatrix()
                                : Eigen::Matrix3d::Identity();
  const Eigen::Matrix3d ref_from_cam = R.transpose();
  // Pixel corners in mrcal coordinates (pixel centres at integers): (x - 0.5, y - 0.5).
  const int W = ph.width, H = ph.height;
  std::vector<mrcal_point2_t> q(size_t(W + 1) * (H + 1));
  for (int y = 0; y <= H; ++y)
    for (int x = 0; x <= W; ++x) {
      q[size_t(y) * (W + 1) + x].x = x - 0.5;
      q[size_t(y) * (W + 1) + x].y = y - 0.5;
    }
  std::vector<mrcal_point3_t> d(q.size());
  if (!mrcal_unproject(d.data(), q.data(), int(q.size()), &model->lensmodel, model->intrinsics))
    throw Error(FileLocation{path}, "mrcal_unproject failed for this lens model");
  // Corner directions -> (u, v); NaN where the direction points away from the source.
  std::vector<double> cu(q.size()), cv(q.size());
  for (size_t i = 0; i < q.size(); ++i) {
    const Eigen::Vector3d c(d[i].x, d[i].y, d[i].z), e = ref_from_cam * c;
    const double len = e.norm();
    if (!(e.z() > 0) || !(len > 0) || !std::isfinite(len)) {
      cu[i] = cv[i] = NAN;
      continue;
    }
    cu[i] = -e.x() / len, cv[i] = e.y() / len;
  }
  std::vector<double> counts(size_t(n) * n, 0.0), area(size_t(n) * n, 0.0), pixel_areas;
  DirectionMapStats st;
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      const size_t c00 = size_t(y) * (W + 1) + x, c10 = c00 + 1, c01 = c00 + W + 1, c11 = c01 + 1;
      const double us[4] = {cu[c00], cu[c10], cu[c11], cu[c01]},
                   vs[4] = {cv[c00], cv[c10], cv[c11], cv[c01]};
      bool ok = true;
      for (int k = 0; k < 4; ++k) ok &= std::isfinite(us[k]);
      if (!ok) continue;
      double a = 0, mu = 0, mv = 0;
      for (int k = 0; k < 4; ++k) {
        a += us[k] * vs[(k + 1) % 4] - us[(k + 1) % 4] * vs[k];  // shoelace
        mu += us[k] / 4, mv += vs[k] / 4;
      }
      a = std::abs(a) / 2;
      st.max_s = std::max(st.max_s, std::hypot(mu, mv));
      const int col = int(std::floor((mu / extent + 1) / 2 * n)),
                row = int(std::floor((1 - mv / extent) / 2 * n));
      if (col < 0 || col >= n || row < 0 || row >= n) continue;
      counts[size_t(row) * n + col] += ph.at(x, y);
      area[size_t(row) * n + col] += a;
      pixel_areas.push_back(a);
      ++st.pixels_used;
    }
  Image map(n, n);
  if (covered) covered->assign(size_t(n) * n, 0);
  for (size_t i = 0; i < map.size(); ++i)
    if (area[i] > 0) {
      map.pixels[i] = float(counts[i] / area[i]);
      if (covered) (*covered)[i] = 1;
    }
  if (!pixel_areas.empty()) {
    std::nth_element(pixel_areas.begin(), pixel_areas.begin() + pixel_areas.size() / 2,
                     pixel_areas.end());
    st.median_pixel_area_uv = pixel_areas[pixel_areas.size() / 2];
  }
  if (stats) *stats = st;
  return map;
}

#else

bool MrcalAvailable() { return false; }

Image DirectionImageToAngularMap(const Image&, const std::string& path, int, double,
                                 std::vector<char>*, DirectionMapStats*) {
  throw Error(FileLocation{path},
              "raymatch was built without mrcal (install libmrcal-dev and reconfigure)");
}

#endif

}  // namespace raymatch::calibrate
