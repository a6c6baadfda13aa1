#include "raymatch/core/array_io.h"

#include <gtest/gtest.h>
#include <hdf5.h>
#include <sys/resource.h>

#include <algorithm>
#include <filesystem>
#include <fstream>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "temp_dir.h"

namespace raymatch {
namespace {

TEST(ArrayIo, NpyAndHdf5RoundTrip) {
  testing::TempDir dir;
  NdArray a;
  a.shape = {2, 3, 4};
  for (int i = 0; i < 24; ++i) a.values.push_back(1.0 + i * 0.5);
  WriteNpy(dir / "a.npy", a);
  const NdArray b = ReadArrayFile(dir / "a.npy");
  EXPECT_EQ(b.shape, a.shape);
  EXPECT_EQ(b.values, a.values);
  WriteHdf5(dir / "a.h5", "/grid/n", a);
  const NdArray c = ReadArrayFile(dir / "a.h5", "/grid/n");
  EXPECT_EQ(c.shape, a.shape);
  EXPECT_EQ(c.values, a.values);
}

// A hand-made float32, Fortran-order .npy (as numpy.asfortranarray(...).astype('<f4') saves).
TEST(ArrayIo, NpyFortranFloat32IsTransposedToCOrder) {
  testing::TempDir dir;
  std::string header = "{'descr': '<f4', 'fortran_order': True, 'shape': (2, 3), }";
  while ((10 + header.size() + 1) % 64) header += ' ';
  header += '\n';
  std::string file = std::string("\x93NUMPY\x01\x00", 8);
  file += char(header.size());
  file += char(0);
  file += header;
  // C-order matrix [[0,1,2],[3,4,5]] stored column-major: 0,3,1,4,2,5
  for (float v : {0.f, 3.f, 1.f, 4.f, 2.f, 5.f}) file.append(reinterpret_cast<char*>(&v), 4);
  std::ofstream(dir / "f.npy", std::ios::binary) << file;
  const NdArray a = ReadNpy(dir / "f.npy");
  ASSERT_EQ(a.shape, (std::vector<size_t>{2, 3}));
  EXPECT_EQ(a.values, (std::vector<double>{0, 1, 2, 3, 4, 5}));
}

TEST(ArrayIo, BadFilesSayWhy) {
  testing::TempDir dir;
  EXPECT_THROW(ReadNpy(dir.Write("x.npy", "hello")), Error);
  EXPECT_THROW(ReadArrayFile(dir.Write("x.csv", "1,2")), Error);
  NdArray a{{2}, {1, 2}};
  WriteHdf5(dir / "a.h5", "n", a);
  try {
    ReadHdf5(dir / "a.h5", "missing");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("no dataset 'missing'"), std::string::npos);
  }
}

// Issue 15 defect 4: a header's declared shape is checked against limits and the file size
// before anything is allocated.
TEST(ArrayIo, NpyDeclaredShapeIsCheckedBeforeAllocating) {
  testing::TempDir dir;
  auto npy = [&](const std::string& shape) {
    std::string header = "{'descr': '<f8', 'fortran_order': False, 'shape': " + shape + ", }";
    while ((10 + header.size() + 1) % 64) header += ' ';
    header += '\n';
    std::string out = "\x93NUMPY";
    out += char(1), out += char(0), out += char(header.size() & 0xff),
        out += char(header.size() >> 8);
    return out + header + std::string(16, '\0');  // two float64 values
  };
  for (auto [shape, what] :
       {std::pair{"(100000, 100000)", "more than the limit"},
        std::pair{"(4294967296, 4294967296, 4294967296)", "more than the limit"},
        std::pair{"(1000, 1000)", "truncated data"}}) {
    try {
      ReadNpy(dir.Write("big.npy", npy(shape)));
      ADD_FAILURE() << shape;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("big.npy: error:"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  }
  EXPECT_EQ(ReadNpy(dir.Write("two.npy", npy("(2,)"))).values, (std::vector<double>{0, 0}));
}

// docs/reliability.md: an HDF5 dataset may declare at most 2^28 values. HDF5 lets a file declare
// a huge chunked dataset without storing any chunk (a few kB on disk); the reader must refuse it
// from the declared extent, naming the file and dataset, before allocating the values (4e8
// doubles would be 3.2 GB).
TEST(ArrayIo, Hdf5DeclaredSizeIsCheckedBeforeAllocating) {
  testing::TempDir dir;
  const std::string path = dir / "huge.h5";
  {
    const hid_t f = H5Fcreate(path.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
    ASSERT_GE(f, 0);
    auto dataset = [&](const char* name, std::vector<hsize_t> dims) {
      const hid_t sp = H5Screate_simple(int(dims.size()), dims.data(), nullptr);
      const hid_t pl = H5Pcreate(H5P_DATASET_CREATE);
      std::vector<hsize_t> chunk;
      for (hsize_t d : dims) chunk.push_back(std::min<hsize_t>(d, 64));
      H5Pset_chunk(pl, int(chunk.size()), chunk.data());
      const hid_t d = H5Dcreate2(f, name, H5T_IEEE_F64LE, sp, H5P_DEFAULT, pl, H5P_DEFAULT);
      EXPECT_GE(d, 0) << name;
      H5Dclose(d);
      H5Pclose(pl);
      H5Sclose(sp);
    };
    dataset("over", {20000, 20000});                      // 4e8 values > 2^28
    dataset("far_over", {1u << 20, 1u << 20, 1u << 20});  // 2^60 values
    dataset("small", {4, 3});  // unwritten chunks read as the fill value 0
    H5Fclose(f);
  }
  ASSERT_LT(std::filesystem::file_size(path), 100000u);
  rusage before{};
  getrusage(RUSAGE_SELF, &before);
  for (const char* name : {"over", "far_over"}) {
    try {
      ReadHdf5(path, name);
      ADD_FAILURE() << name << " was read";
    } catch (const Error& e) {
      const std::string m = e.what();
      EXPECT_NE(m.find("huge.h5:" + std::string(name) + ": error:"), std::string::npos) << m;
      EXPECT_NE(m.find("more than the limit of 268435456 values"), std::string::npos) << m;
    }
  }
  rusage after{};
  getrusage(RUSAGE_SELF, &after);
  EXPECT_LT(after.ru_maxrss - before.ru_maxrss, 100 * 1024)
      << "peak RSS grew by " << after.ru_maxrss - before.ru_maxrss << " kB";
  const NdArray small = ReadHdf5(path, "small");
  EXPECT_EQ(small.shape, (std::vector<size_t>{4, 3}));
  EXPECT_EQ(small.values, std::vector<double>(12, 0.0));
}

// The registry of temporaries that a signal handler removes (core/atomic_file.h) holds only
// writes in flight: every finished or failed write unregisters its temporary (a leak would fill
// the fixed table and leave later temporaries unprotected).
TEST(AtomicFile, TemporariesAreUnregisteredAfterCommitAndFailure) {
  testing::TempDir dir;
  const int before = RegisteredTemporaries();
  WriteTextFileAtomic(dir / "a.txt", "a");
  WriteFloatImage(dir / "a.tif", Image(4, 3, 1.f), "test");
  NdArray a;
  a.shape = {2};
  a.values = {1, 2};
  WriteHdf5(dir / "a.h5", "n", a);
  WriteNpy(dir / "a.npy", a);
  EXPECT_THROW(WriteTextFileAtomic(dir / "missing/a.txt", "a"), Error);
  EXPECT_THROW(WriteFloatImage(dir / "missing/a.tif", Image(4, 3, 1.f), "test"), Error);
  EXPECT_THROW(WriteHdf5(dir / "missing/a.h5", "n", a), Error);
  EXPECT_THROW(CommitTemporary(TemporaryPathFor(dir / "b.txt"), dir / "b.txt"),
               Error);  // nothing to move
  EXPECT_EQ(RegisteredTemporaries(), before);
  for (const auto& e : std::filesystem::directory_iterator(dir.path()))
    EXPECT_EQ(e.path().filename().string().find(".partial-"), std::string::npos) << e.path();
}

// Issue 25: a command that fails removes the output folders it made while they are still empty
// (EnsureDirectory records them), innermost first; folders that existed or hold a file stay.
TEST(AtomicFile, CreatedFoldersAreRemovedWhileEmpty) {
  testing::TempDir dir;
  RemoveCreatedEmptyDirectories();  // forget folders earlier tests made
  namespace fs = std::filesystem;
  fs::create_directories(dir / "old");
  EnsureDirectory(dir / "old/a/b/c/");
  EnsureDirectory(dir / "new/x");
  EnsureDirectory(dir / "kept/y");
  WriteTextFileAtomic(dir / "kept/y/file.txt", "x");
  EnsureDirectory(dir / "old");                   // existed: not recorded
  EXPECT_EQ(RemoveCreatedEmptyDirectories(), 5);  // old/a/b/c, old/a/b, old/a, new/x, new
  EXPECT_TRUE(fs::is_directory(dir / "old"));
  EXPECT_FALSE(fs::exists(dir / "old/a"));
  EXPECT_FALSE(fs::exists(dir / "new"));
  EXPECT_TRUE(fs::exists(dir / "kept/y/file.txt"));
  EXPECT_EQ(RemoveCreatedEmptyDirectories(), 0);  // forgotten once done
  EXPECT_TRUE(fs::is_directory(dir.path()));
}

}  // namespace
}  // namespace raymatch
