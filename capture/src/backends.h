#pragma once
// Backend entry points (private to the capture library).
#include <memory>
#include <string>
#include <vector>

#include "raymatch/capture/camera.h"

namespace raymatch::capture::internal {

std::unique_ptr<Camera> OpenSimCamera(const std::string& scene_path);

std::vector<CameraInfo> ListV4l2(std::vector<std::string>* notes);
std::unique_ptr<Camera> OpenV4l2(const std::string& device);

#ifdef RAYMATCH_WITH_LIBCAMERA
std::vector<CameraInfo> ListLibcamera(std::vector<std::string>* notes);
std::unique_ptr<Camera> OpenLibcamera(const std::string& id);
std::string LibcameraVersion();
#endif

}  // namespace raymatch::capture::internal
