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


// Issue 15 defect 4: a header's declared shape is checked against limits and the file size
// before anything is allocated.
TEST(ArrayIo, NpyDeclaredShapeIsCheckedBeforeAllocating) {
  testing::TempDir dir;
  auto npy = [&](const std::string& shape) {
    std::string header = "{'descr': '<f8', 'fortran_order': False, 'shape': " + shape + ", }";
    while ((10 + header.size() + 1) % 64) header += ' ';
    header += '\n';
    std::string out = "\x93NUMPY";
    out += char(1), out += char(0), out += char(header.size() & 0xff), out += char(header.size() >> 8);
    return out + header + std::string(16, '\0');  // two float64 values
  };
  for (auto [shape, what] : {std::pair{"(100000, 100000)", "more than the limit"},
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

}  // namespace
}  // namespace raymatch
