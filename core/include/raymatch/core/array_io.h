#pragma once
// N-dimensional numeric arrays from NumPy .npy files and HDF5 datasets (CFD grids, index and
// density fields). Values are converted to double; C (row-major) order, last axis fastest.
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace raymatch {

struct NdArray {
  std::vector<size_t> shape;   ///< e.g. {nz, nr} or {nz, ny, nx}
  std::vector<double> values;  ///< row-major, size = product of shape
  size_t size() const { return values.size(); }
};

/// Most values an array file may declare (2^28, 2 GiB as double); checked before allocating.
inline constexpr uint64_t kMaxArrayValues = uint64_t(1) << 28;

/// The number of values of `shape`; throws Error naming `path` for an empty shape, a zero
/// dimension or more than kMaxArrayValues values (no overflow).
size_t CheckedValueCount(const std::string& path, const std::vector<size_t>& shape);

/// Reads a .npy file (format versions 1-3; little/big-endian float32/float64/int/uint of 1-8
/// bytes; C or Fortran order, Fortran is transposed to C order). Throws Error naming the file.
NdArray ReadNpy(const std::string& path);

/// Writes a float64 C-order .npy file atomically (tests, exported grids).
void WriteNpy(const std::string& path, const NdArray& array);

/// Reads an HDF5 dataset (any numeric type) as double. Throws Error naming file and dataset.
NdArray ReadHdf5(const std::string& path, const std::string& dataset);

/// Writes a float64 HDF5 dataset (creating the file; tests, exported grids).
void WriteHdf5(const std::string& path, const std::string& dataset, const NdArray& array);

/// Reads .npy, or .h5/.hdf5 with `dataset`, by extension.
NdArray ReadArrayFile(const std::string& path, const std::string& dataset = "");

}  // namespace raymatch
