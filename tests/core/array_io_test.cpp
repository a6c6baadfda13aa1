#include "raymatch/core/array_io.h"

#include <gtest/gtest.h>

#include <fstream>

#include "raymatch/core/error.h"
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

}  // namespace
}  // namespace raymatch
