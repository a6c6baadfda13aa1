#pragma once
// PNG figures for the reports, drawn by PLplot (Debian's libplplot-dev, cairo PNG device):
// x-y plots with labelled axes, error bars, shaded bands and legends; false-colour maps with
// labelled axes and a colour bar; grids of images on one shared intensity scale.
// docs/figures.md says why PLplot and how each report figure is made.
//
// Figures are written atomically (a registered `*.partial-*` temporary, checked to be a whole
// PNG, renamed into place: core/atomic_file.h). PLplot's state is global, so the helpers draw one
// figure at a time in the process (a mutex; safe to call from several threads). Throws
// raymatch::Error (a std::runtime_error) naming the file when it cannot be written (with the
// reason: disk full, no permission) or when PLplot's cairo PNG device is not available.
#include <array>
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::compare {

/// Colour maps for false-colour figures.
enum class ColourMap {
  kViridis,          ///< perceptually uniform, dark (low) to yellow (high)
  kViridisReversed,  ///< yellow (low) to dark (high): "bright = good" for distances
  kGrey,             ///< black (low) to white (high)
  kDiverging,        ///< blue (low) - white (middle) - red (high), for signed data
};

/// One curve of an x-y plot.
struct Series {
  std::vector<double> x, y, yerr;  ///< yerr empty or one per point (+- error bars)
  bool points = false;             ///< markers (with error bars) instead of a line
  bool joined = false;             ///< with `points`: a line through the markers too
  std::string label;               ///< legend entry; no entry when empty
  /// A shaded band from band_lo to band_hi (one value per x) drawn beneath the curve, in the
  /// curve's colour; empty for none.
  std::vector<double> band_lo, band_hi;
};

/// One panel of an x-y plot (panels are stacked vertically in one figure).
struct PlotPanel {
  std::vector<Series> series;  ///< colours in order: blue, red, green, orange, purple
  std::string title, xlabel, ylabel;
  /// Logarithmic axes (values must be > 0). PLplot labels only whole decades, so an axis whose
  /// values span less than a factor of 10 stays linear; " (log scale)" is appended to the label
  /// of an axis drawn logarithmically.
  bool log_x = false;
  bool log_y = false;
};

/// Writes stacked x-y panels, `width` x `panel_height` pixels each.
void WritePlot(const std::string& path, const std::vector<PlotPanel>& panels, int width = 760,
               int panel_height = 440);

/// One panel with one title and axis labels.
void WritePlot(const std::string& path, const std::vector<Series>& series, const std::string& title,
               const std::string& xlabel, const std::string& ylabel);

/// A symbol drawn over a map at axis coordinates (x, y).
struct MapMarker {
  double x = 0, y = 0;
  bool emphasis = true;  ///< true: white open square (e.g. best match); false: red dot
};

/// A false-colour map of an image with axes and a colour bar.
struct MapPlot {
  Image image;  ///< image.at(x, y); row y = 0 is drawn at the top unless `rows_up`
  /// Axis coordinates of the left, right, top and bottom image edges (e.g. um at the object);
  /// all 0: pixel edges, columns 0 .. width to the right and rows 0 .. height downwards.
  double x_left = 0, x_right = 0, y_top = 0, y_bottom = 0;
  /// Optional non-uniform cell edges along x (width + 1 values) and y (height + 1 values, for
  /// row 0 first); override the four edges above when given.
  std::vector<double> x_edges, y_edges;
  double lo = 0, hi = 0;  ///< colour range (values outside clamp); lo == hi: the data's range
  ColourMap map = ColourMap::kViridis;
  std::string title, xlabel, ylabel, colour_label;
  std::vector<MapMarker> markers;
  std::string marker_legend;  ///< a line under the plot explaining the markers; none when empty
  int max_side_px = 560;      ///< the longer side of the map in the figure, in pixels
};

/// Writes a map with axes and a colour bar.
void WriteMap(const std::string& path, const MapPlot& plot);

/// Images shown as tiles in rows and columns, all on one intensity scale [lo, hi] with one
/// colour bar (e.g. experiment above simulation in a focus scan).
struct ImageGrid {
  std::vector<std::vector<Image>> rows;  ///< rows[r][c]; all images the same size
  std::vector<std::string> row_labels;   ///< one per row (left of the row)
  /// tile_labels[r][c] is written above tile (r, c); missing or empty: none.
  std::vector<std::vector<std::string>> tile_labels;
  double lo = 0, hi = 1;
  ColourMap map = ColourMap::kGrey;
  std::string title;  ///< above the grid; '\n' starts a new line
  std::string colour_label;
  int tile_px = 150;  ///< tile side in pixels (the longer image side)
};

/// Writes an image grid with its labels and the shared colour bar.
void WriteImageGrid(const std::string& path, const ImageGrid& grid);

/// An image as a false-colour (viridis) map scaled to [0, its maximum], with a colour bar;
/// `zoom` scales the map's size.
void WriteFalseColour(const std::string& path, const Image& img, int zoom);

/// The same mapped linearly from [lo, hi] (values outside clamp to the ends).
void WriteFalseColour(const std::string& path, const Image& img, double lo, double hi, int zoom);

/// A residual map in standard deviations: -4 blue, 0 white, +4 red, clamped; its axes in um at
/// the object from the image centre where `object_pixel_um` (the camera's pixel at the object)
/// is above 0, else in pixels. The caller sets the title and the colour bar's label.
MapPlot ResidualMapPlot(const Image& residual, double object_pixel_um);

}  // namespace raymatch::compare
