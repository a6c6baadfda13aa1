#pragma once
// Shared helpers of the Python bindings: NumPy <-> raymatch::Image, JSON -> Python objects.
//
// Images out of the libraries become NumPy arrays without a copy: the Image's pixel vector is
// moved into a capsule that the array owns. Images into the libraries are copied once into the
// library's own float32 Image (it owns its pixels), converting the dtype where needed.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::python {

namespace py = pybind11;

/// A 2-D float32 array (rows = height, columns = width) owning the image's pixels (moved).
inline py::array_t<float> ToArray(Image&& img) {
  auto* pixels = new std::vector<float>(std::move(img.pixels));
  py::capsule owner(pixels, [](void* p) { delete static_cast<std::vector<float>*>(p); });
  const py::ssize_t h = img.height, w = img.width;
  return py::array_t<float>({h, w}, {w * py::ssize_t(sizeof(float)), py::ssize_t(sizeof(float))},
                            pixels->data(), owner);
}

/// A read-only 2-D view of an image that lives inside `owner` (no copy; keeps owner alive).
inline py::array_t<float> ViewArray(const Image& img, py::handle owner) {
  const py::ssize_t h = img.height, w = img.width;
  py::array_t<float> a({h, w}, {w * py::ssize_t(sizeof(float)), py::ssize_t(sizeof(float))},
                       img.pixels.data(), owner);
  py::detail::array_proxy(a.ptr())->flags &= ~py::detail::npy_api::NPY_ARRAY_WRITEABLE_;
  return a;
}

/// A raymatch Image (float32 copy) from any 2-D array-like; `what` names it in errors.
inline Image FromArray(const py::handle& obj, const char* what) {
  auto a = py::array_t<float, py::array::c_style | py::array::forcecast>::ensure(obj);
  if (!a) {
    PyErr_Clear();
    throw py::type_error(std::string(what) + ": expected a 2-D numeric array (rows, columns)");
  }
  if (a.ndim() != 2)
    throw py::value_error(std::string(what) + ": expected a 2-D array (rows, columns), got " +
                          std::to_string(a.ndim()) + " dimension(s)");
  Image img(static_cast<int>(a.shape(1)), static_cast<int>(a.shape(0)));
  std::copy(a.data(), a.data() + img.pixels.size(), img.pixels.begin());
  return img;
}

inline std::vector<Image> FromArrays(const py::iterable& seq, const char* what) {
  std::vector<Image> out;
  for (py::handle h : seq) out.push_back(FromArray(h, what));
  return out;
}

/// JSON -> Python dict/list/... through Python's json module (exact for 64-bit integers).
inline py::object ToPython(const nlohmann::json& j) {
  return py::module_::import("json").attr("loads")(j.dump());
}

/// A 2-D float64 array from rows of equal length (copied; small matrices only).
inline py::array_t<double> ToMatrix(const std::vector<std::vector<double>>& rows) {
  const py::ssize_t n = rows.size(), m = rows.empty() ? 0 : rows[0].size();
  py::array_t<double> a({n, m});
  auto r = a.mutable_unchecked<2>();
  for (py::ssize_t i = 0; i < n; ++i)
    for (py::ssize_t k = 0; k < m; ++k) r(i, k) = rows[i][k];
  return a;
}

/// A path argument: str or os.PathLike.
inline std::string PathArg(const py::handle& p) {
  return py::str(py::module_::import("os").attr("fspath")(p));
}

void BindScene(py::module_& m);        // module.cpp: scenes and simulate
void BindCompare(py::module_& m);      // compare.cpp
void BindCalibrate(py::module_& m);    // calibrate_fit.cpp
void BindFit(py::module_& m);          // calibrate_fit.cpp
void BindSensitivity(py::module_& m);  // calibrate_fit.cpp

}  // namespace raymatch::python
