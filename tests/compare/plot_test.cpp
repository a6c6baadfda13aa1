// The PLplot figure helpers (compare/plot.h): each writes a PNG of the stated size, leaves no
// temporary file, draws what it is given (pixels differ where the data differ) and refuses an
// empty image grid.
#include "raymatch/compare/plot.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <thread>
#include <vector>

#include "raymatch/core/image_io.h"
#include "temp_dir.h"

namespace raymatch::compare {
namespace {

namespace fs = std::filesystem;

/// Number of pixels whose grey value differs between two images of the same size.
size_t DifferentPixels(const Image& a, const Image& b) {
  size_t n = 0;
  for (size_t i = 0; i < a.pixels.size() && i < b.pixels.size(); ++i)
    n += a.pixels[i] != b.pixels[i];
  return n;
}

size_t FilesIn(const std::string& dir) {
  size_t n = 0;
  for (const auto& e : fs::directory_iterator(dir)) n += e.is_regular_file();
  return n;
}

TEST(Plot, XyPlotHasTheRequestedSizeAndShowsItsData) {
  testing::TempDir dir;
  Series s;
  s.label = "a line";
  for (int i = 0; i < 20; ++i) s.x.push_back(i), s.y.push_back(std::sin(i * 0.3));
  s.band_lo = s.y, s.band_hi = s.y;
  for (double& v : s.band_lo) v -= 0.1;
  for (double& v : s.band_hi) v += 0.1;
  PlotPanel p;
  p.series = {s};
  p.title = "t", p.xlabel = "x (um)", p.ylabel = "y";
  WritePlot(dir / "a.png", {p, p}, 400, 300);  // two stacked panels
  const Image a = ReadImage(dir / "a.png");    // grey: the mean of R, G and B
  EXPECT_EQ(a.width, 400);
  EXPECT_EQ(a.height, 600);
  EXPECT_EQ(FilesIn(dir.path()), 1u) << "a temporary file was left behind";
  // Other data, same axes text: the drawing differs.
  for (double& v : p.series[0].y) v = -v;
  WritePlot(dir / "b.png", {p, p}, 400, 300);
  EXPECT_GT(DifferentPixels(a, ReadImage(dir / "b.png")), 500u);
}

TEST(Plot, MapAndGridAreWritten) {
  testing::TempDir dir;
  Image img(32, 16);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 32; ++x) img.at(x, y) = float(x - 16);
  MapPlot m;
  m.image = img;
  m.map = ColourMap::kDiverging;
  m.lo = -16, m.hi = 16;
  m.x_left = -8, m.x_right = 8, m.y_top = 4, m.y_bottom = -4;
  m.colour_label = "value (units)";
  m.markers = {{0, 0, true}, {1, 1, false}};
  m.marker_legend = "box: a marker";
  WriteMap(dir / "m.png", m);
  EXPECT_GT(ReadImage(dir / "m.png").width, 32 * 10);  // scaled to max_side_px, with margins
  ImageGrid g;
  g.rows = {{img, img, img}, {img, img, img}, {img}};  // a short last row (a montage's wrap)
  g.tile_labels = {{"a", "b", "c"}, {}, {"d"}};
  g.row_labels = {"top", "middle", "bottom"};
  g.lo = -16, g.hi = 16;
  g.title = "line one\nline two";
  WriteImageGrid(dir / "g.png", g);
  EXPECT_TRUE(fs::exists(dir / "g.png"));
  EXPECT_EQ(FilesIn(dir.path()), 2u);
  EXPECT_THROW(WriteImageGrid(dir / "empty.png", ImageGrid{}), std::runtime_error);
  EXPECT_FALSE(fs::exists(dir / "empty.png"));
}

// Each image pixel gets its own cell of its own colour (PLplot's plimagefr puts values on cell
// corners; drawn naively a 2 x 2 image would show one cell).
TEST(Plot, EveryPixelIsDrawn) {
  testing::TempDir dir;
  Image img(2, 2);
  img.pixels = {0.f, 1.f / 3, 2.f / 3, 1.f};
  MapPlot m;
  m.image = img;
  m.map = ColourMap::kGrey;
  m.lo = 0, m.hi = 1;
  m.max_side_px = 300;
  WriteMap(dir / "m.png", m);
  const Image out = ReadImage(dir / "m.png");  // 8-bit grey: the mean of R, G and B
  size_t dark_grey = 0, light_grey = 0;
  for (float v : out.pixels)
    dark_grey += std::abs(v - 85) <= 2, light_grey += std::abs(v - 170) <= 2;
  // Each cell is about 150 x 150 px; the colour bar has a few pixels of each grey.
  EXPECT_GT(dark_grey, 15000u);
  EXPECT_GT(light_grey, 15000u);
}

// PLplot's state is global: figures written from several threads at once all come out whole
// and the same as when written alone.
TEST(Plot, ConcurrentFiguresAreWhole) {
  testing::TempDir dir;
  Series s;
  for (int i = 0; i < 50; ++i) s.x.push_back(i), s.y.push_back(i * i);
  WritePlot(dir / "alone.png", {s}, "t", "x", "y");
  const Image alone = ReadImage(dir / "alone.png");
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t)
    threads.emplace_back(
        [&, t] { WritePlot(dir / ("t" + std::to_string(t) + ".png"), {s}, "t", "x", "y"); });
  for (std::thread& t : threads) t.join();
  for (int t = 0; t < 4; ++t)
    EXPECT_EQ(DifferentPixels(alone, ReadImage(dir / ("t" + std::to_string(t) + ".png"))), 0u) << t;
}

// A figure that cannot be written (its folder is a file) is an error naming it, never a prompt
// on stdin (what PLplot does when it cannot open its output) and never a partial file.
TEST(Plot, UnwritablePathIsAnErrorNamingIt) {
  testing::TempDir dir;
  dir.Write("file", "x");
  const std::string bad = dir / "file/figure.png";
  try {
    WritePlot(bad, {Series{{0, 1}, {0, 1}}}, "t", "x", "y");
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("file"), std::string::npos) << e.what();
  }
  EXPECT_EQ(FilesIn(dir.path()), 1u);
}

}  // namespace
}  // namespace raymatch::compare
