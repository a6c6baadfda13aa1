#include "raymatch/core/array_io.h"

#include <hdf5.h>

#include <algorithm>
#include <bit>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <regex>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"

namespace raymatch {

namespace {

[[noreturn]] void Fail(const std::string& path, const std::string& msg) {
  throw Error(FileLocation{path}, msg);
}

template <class T>
double Load(const char* p, bool swap) {
  T v;
  char b[sizeof(T)];
  std::memcpy(b, p, sizeof(T));
  if (swap) std::reverse(b, b + sizeof(T));
  std::memcpy(&v, b, sizeof(T));
  return static_cast<double>(v);
}

}  // namespace

size_t CheckedValueCount(const std::string& path, const std::vector<size_t>& shape) {
  if (shape.empty()) Fail(path, "empty array (no dimensions)");
  uint64_t n = 1;
  std::string dims;
  for (size_t d : shape) dims += (dims.empty() ? "" : " x ") + std::to_string(d);
  for (size_t d : shape) {
    if (d == 0) Fail(path, "empty array (shape " + dims + ")");
    if (d > kMaxArrayValues || n * d > kMaxArrayValues)
      Fail(path, "shape " + dims + " is more than the limit of " + std::to_string(kMaxArrayValues) +
                     " values");
    n *= d;
  }
  return static_cast<size_t>(n);
}

NdArray ReadNpy(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) Fail(path, "cannot open file for reading");
  char magic[8];
  if (!in.read(magic, 8) || std::memcmp(magic, "\x93NUMPY", 6) != 0)
    Fail(path, "not a NumPy .npy file (bad magic)");
  const int major = magic[6];
  size_t hlen = 0;
  if (major == 1) {
    unsigned char b[2];
    in.read(reinterpret_cast<char*>(b), 2);
    hlen = b[0] | (b[1] << 8);
  } else if (major == 2 || major == 3) {
    unsigned char b[4];
    in.read(reinterpret_cast<char*>(b), 4);
    hlen = b[0] | (b[1] << 8) | (b[2] << 16) | (size_t(b[3]) << 24);
  } else {
    Fail(path, "unsupported .npy format version " + std::to_string(major));
  }
  if (!in || hlen > (1u << 20))
    Fail(path, "bad .npy header length " + std::to_string(hlen) + " (expected at most 1 MiB)");
  std::string header(hlen, '\0');
  if (!in.read(header.data(), hlen)) Fail(path, "truncated .npy header");
  std::smatch m;
  if (!std::regex_search(header, m, std::regex("'descr':\\s*'([<>|=])([fiub])(\\d+)'")))
    Fail(path, "unsupported dtype in header: " + header);
  const char endian = m[1].str()[0], kind = m[2].str()[0];
  const int bytes = m[3].str().size() > 2 ? 0 : std::stoi(m[3].str());
  const bool fortran = std::regex_search(header, std::regex("'fortran_order':\\s*True"));
  if (!std::regex_search(header, m, std::regex("'shape':\\s*\\(([^)]*)\\)")))
    Fail(path, "no shape in header");
  NdArray a;
  const std::string dims = m[1].str();
  const std::regex number("\\d+");
  for (std::sregex_iterator it(dims.begin(), dims.end(), number), end; it != end; ++it)
    if (it->str().size() > 18)
      Fail(path, "dimension " + it->str() + " in the header is too large");
    else
      a.shape.push_back(std::stoull(it->str()));
  if (bytes != 1 && bytes != 2 && bytes != 4 && bytes != 8)
    Fail(path, "unsupported dtype " + std::string(1, kind) + std::to_string(bytes));
  const size_t n = CheckedValueCount(path, a.shape);
  // The header's shape must fit in what the file holds before anything is allocated.
  const std::streamoff data_start = in.tellg();
  in.seekg(0, std::ios::end);
  const std::streamoff data_bytes = in.tellg() - data_start;
  in.seekg(data_start);
  if (data_bytes < 0 || uint64_t(data_bytes) < uint64_t(n) * bytes)
    Fail(path, "truncated data: the header's shape needs " + std::to_string(n) + " values (" +
                   std::to_string(uint64_t(n) * bytes) + " bytes), the file holds " +
                   std::to_string(std::max<std::streamoff>(data_bytes, 0)) + " bytes");
  std::vector<char> raw(n * bytes);
  if (!in.read(raw.data(), raw.size()))
    Fail(path, "truncated data: expected " + std::to_string(n) + " values");
  const bool little = std::endian::native == std::endian::little;
  const bool swap = (endian == '<' && !little) || (endian == '>' && little);
  a.values.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const char* p = raw.data() + i * bytes;
    double v;
    if (kind == 'f' && bytes == 8)
      v = Load<double>(p, swap);
    else if (kind == 'f' && bytes == 4)
      v = Load<float>(p, swap);
    else if (kind == 'i' && bytes == 8)
      v = Load<int64_t>(p, swap);
    else if (kind == 'i' && bytes == 4)
      v = Load<int32_t>(p, swap);
    else if (kind == 'i' && bytes == 2)
      v = Load<int16_t>(p, swap);
    else if (kind == 'i' && bytes == 1)
      v = Load<int8_t>(p, swap);
    else if (kind == 'u' && bytes == 8)
      v = Load<uint64_t>(p, swap);
    else if (kind == 'u' && bytes == 4)
      v = Load<uint32_t>(p, swap);
    else if (kind == 'u' && bytes == 2)
      v = Load<uint16_t>(p, swap);
    else if (kind == 'u' && bytes == 1)
      v = Load<uint8_t>(p, swap);
    else
      Fail(path, "unsupported dtype " + std::string(1, kind) + std::to_string(bytes));
    a.values[i] = v;
  }
  if (fortran && a.shape.size() > 1) {  // column-major -> row-major
    std::vector<double> c(n);
    const size_t nd = a.shape.size();
    std::vector<size_t> idx(nd, 0);
    for (size_t f = 0; f < n; ++f) {
      size_t ci = 0;
      for (size_t d = 0; d < nd; ++d) ci = ci * a.shape[d] + idx[d];
      c[ci] = a.values[f];
      for (size_t d = 0; d < nd; ++d) {  // Fortran order: first index fastest
        if (++idx[d] < a.shape[d]) break;
        idx[d] = 0;
      }
    }
    a.values.swap(c);
  }
  return a;
}

void WriteNpy(const std::string& path, const NdArray& a) {
  std::string shape = "(";
  for (size_t d : a.shape) shape += std::to_string(d) + ", ";
  if (a.shape.size() > 1) shape.resize(shape.size() - 2);
  shape += ")";
  std::string header = "{'descr': '<f8', 'fortran_order': False, 'shape': " + shape + ", }";
  while ((10 + header.size() + 1) % 64) header += ' ';
  header += '\n';
  std::string out = "\x93NUMPY";
  out += char(1);
  out += char(0);
  out += char(header.size() & 0xff);
  out += char(header.size() >> 8);
  out += header;
  out.append(reinterpret_cast<const char*>(a.values.data()), a.values.size() * sizeof(double));
  WriteTextFileAtomic(path, out);
}

NdArray ReadHdf5(const std::string& path, const std::string& dataset) {
  if (!std::filesystem::exists(path)) Fail(path, "file not found");
  H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);  // we report errors ourselves
  const hid_t f = H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT);
  if (f < 0) Fail(path, "not an HDF5 file");
  const hid_t d = H5Dopen2(f, dataset.c_str(), H5P_DEFAULT);
  if (d < 0) {
    H5Fclose(f);
    Fail(path, "no dataset '" + dataset + "'");
  }
  const hid_t sp = H5Dget_space(d);
  const int nd = H5Sget_simple_extent_ndims(sp);
  std::vector<hsize_t> dims(std::max(nd, 0));
  H5Sget_simple_extent_dims(sp, dims.data(), nullptr);
  NdArray a;
  for (hsize_t x : dims) a.shape.push_back(x);
  size_t n = 0;
  try {
    n = CheckedValueCount(path + ":" + dataset, a.shape);
  } catch (const Error&) {
    H5Sclose(sp);
    H5Dclose(d);
    H5Fclose(f);
    throw;
  }
  a.values.resize(n);
  const herr_t st =
      n ? H5Dread(d, H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, a.values.data()) : -1;
  H5Sclose(sp);
  H5Dclose(d);
  H5Fclose(f);
  if (st < 0) Fail(path, "cannot read dataset '" + dataset + "' as numbers");
  return a;
}

void WriteHdf5(const std::string& path, const std::string& dataset, const NdArray& a) {
  const std::filesystem::path tmp = TemporaryPathFor(path);
  H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr);
  const hid_t f = H5Fcreate(tmp.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
  if (f < 0) {
    const std::string hint = WriteFailureHint(path);
    DiscardTemporary(tmp);
    Fail(path, "cannot create HDF5 file" + (hint.empty() ? "" : ": " + hint));
  }
  std::vector<hsize_t> dims(a.shape.begin(), a.shape.end());
  const hid_t sp = H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr);
  const hid_t lcpl = H5Pcreate(H5P_LINK_CREATE);
  H5Pset_create_intermediate_group(lcpl, 1);  // "/grid/n" creates group "/grid"
  const hid_t d =
      H5Dcreate2(f, dataset.c_str(), H5T_IEEE_F64LE, sp, lcpl, H5P_DEFAULT, H5P_DEFAULT);
  H5Pclose(lcpl);
  const herr_t st =
      d < 0 ? herr_t(-1)
            : H5Dwrite(d, H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, a.values.data());
  const herr_t closed =
      (d < 0 ? 0 : H5Dclose(d)) | H5Sclose(sp) | H5Fclose(f);  // a full disk can show here
  if (st < 0 || closed < 0) {
    const std::string hint = WriteFailureHint(path);
    DiscardTemporary(tmp);
    Fail(path, "cannot write dataset '" + dataset + "'" + (hint.empty() ? "" : ": " + hint));
  }
  CommitTemporary(tmp, path);
}

NdArray ReadArrayFile(const std::string& path, const std::string& dataset) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  if (ext == ".npy") return ReadNpy(path);
  if (ext == ".h5" || ext == ".hdf5") {
    if (dataset.empty()) Fail(path, "an HDF5 grid needs 'dataset' (the dataset path)");
    return ReadHdf5(path, dataset);
  }
  Fail(path, "unsupported grid file type '" + ext + "' (expected .npy, .h5 or .hdf5)");
}

}  // namespace raymatch
