#pragma once
// Writing an OpenCV BGR drawing as an RGB PNG (atomic, through core's image I/O).
#include <opencv2/imgproc.hpp>
#include <string>

#include "raymatch/core/image_io.h"

namespace raymatch::compare {

inline void WriteBgrPng(const std::string& path, const cv::Mat& bgr) {
  cv::Mat rgb;
  cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
  WriteRgbPng(path, rgb.cols, rgb.rows, rgb.ptr<unsigned char>());
}

}  // namespace raymatch::compare
