#pragma once
// Light field from images taken by a camera focused at infinity, whose mrcal .cameramodel maps
// pixels to directions (mrcal 2.2 C API: mrcal_read_cameramodel_file, mrcal_unproject).
//
// Frame (docs/calibration.md): the camera sits downstream in the light cone and looks back at
// the source. Its reference frame ("extrinsics" rt_cam_ref of the model) has x along the light
// field's +x, y along -y and z along -z (upstream), so an upright camera with identity
// extrinsics sees the source ahead. A pixel that unprojects to the reference-frame vector
// d = (a, b, c) (c > 0) receives the light travelling in the direction -(a, -b, -c) of the
// light frame, i.e. direction cosines u = -a/|d|, v = b/|d|: the image is the (u, v) map
// turned by 180 degrees.
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::calibrate {

/// True when the library was built with mrcal (RAYMATCH_WITH_MRCAL).
bool MrcalAvailable();

struct DirectionMapStats {
  size_t pixels_used = 0;           ///< pixels whose direction fell inside the map
  double median_pixel_area_uv = 0;  ///< solid extent of a pixel in du dv
  double max_s = 0;                 ///< largest sqrt(u^2 + v^2) seen by the camera
};

/// Angular radiance per du dv (photons per unit du dv) from one image in photons: every pixel
/// is unprojected at its four corners (mrcal pixel centres are at integer coordinates, ours at
/// +0.5), its counts go to the map cell of its centre direction, and each cell's radiance is
/// the sum of counts over the sum of the pixels' (u, v) areas (a ratio estimator that needs no
/// Jacobian and is unbiased for partly covered cells). `covered` flags cells with data.
/// Throws Error when the model cannot be read, the image size differs from the model's
/// imager size, or mrcal is not available.
Image DirectionImageToAngularMap(const Image& photons, const std::string& cameramodel, int n,
                                 double extent, std::vector<char>* covered,
                                 DirectionMapStats* stats);

}  // namespace raymatch::calibrate
