// Report figures through PLplot's C++ API and its cairo PNG device ("pngcairo").
// PLplot draws the axes, ticks, tick labels, titles, legends, colour bars, images and error
// bars; this file only chooses sizes, colours and what goes into each panel.
#include "raymatch/compare/plot.h"

#include <plplot/plstream.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <mutex>
#include <stdexcept>

#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"

namespace fs = std::filesystem;

namespace raymatch::compare {

namespace {

// cmap0 (indexed colours). 0 is the background.
constexpr int kWhite = 0, kBlack = 1, kGrid = 7, kMarkerWhite = 8;
constexpr int kSeriesColour = 2;  // 2..6: blue, red, green, orange, purple
constexpr int kBandColour = 9;    // 9..13: the same, translucent
constexpr int kSeriesColours = 5;

/// PLplot treats '#' as its escape character; user text (file names, keys) gets it doubled.
std::string Esc(const std::string& s) {
  std::string o;
  for (char c : s) {
    o += c;
    if (c == '#') o += '#';
  }
  return o;
}

/// True when PLplot was built with the cairo PNG device (Debian: plplot-driver-cairo).
bool HavePngCairo() {
  static const bool have = [] {
    // The caller owns the arrays; on return n holds the number of devices filled in.
    std::vector<const char*> menu(128), names(128);
    const char** m = menu.data();
    const char** d = names.data();
    int n = int(menu.size());
    plgDevs(&m, &d, &n);
    for (int i = 0; i < n; ++i)
      if (d[i] && std::string(d[i]) == "pngcairo") return true;
    return false;
  }();
  return have;
}

/// True when `path` holds a whole PNG (signature first, IEND chunk last): the cairo device does
/// not report a failed write (e.g. a full disk), so the file is checked instead.
bool WholePng(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  static const std::string kSignature = "\x89PNG\r\n\x1a\n";
  static const std::string kEnd = std::string("IEND\xae\x42\x60\x82", 8);
  return bytes.size() > kSignature.size() + kEnd.size() && bytes.compare(0, 8, kSignature) == 0 &&
         bytes.compare(bytes.size() - kEnd.size(), kEnd.size(), kEnd) == 0;
}

/// One PNG figure: a PLplot stream on the pngcairo device writing a registered temporary
/// (core/atomic_file.h) that Finish() checks and renames into place.
class Figure {
 public:
  Figure(const std::string& path, int width, int height, int nx_sub = 1, int ny_sub = 1)
      : lock_(Mutex()), path_(path) {
    if (!HavePngCairo())
      throw Error("PLplot has no pngcairo device: install plplot-driver-cairo (writing " + path +
                  ")");
    if (!path_.parent_path().empty()) EnsureDirectory(path_.parent_path());
    tmp_ = TemporaryPathFor(path_);
    // Create the file here: PLplot, when it cannot open its output, asks for another name on
    // stdin and exits.
    if (!std::ofstream(tmp_, std::ios::binary)) {
      DiscardTemporary(tmp_);
      const std::string hint = WriteFailureHint(path_);
      throw Error("cannot write " + path + (hint.empty() ? "" : ": " + hint));
    }
    pls_ = std::make_unique<plstream>();
    pls_->sdev("pngcairo");
    pls_->sfnam(tmp_.string().c_str());
    pls_->spage(0, 0, width, height, 0, 0);
    // Palette (r, g, b, alpha): background, ink, five series colours, grid, white, bands.
    const int r[] = {255, 0, 31, 214, 44, 230, 148, 215, 255, 31, 214, 44, 230, 148};
    const int g[] = {255, 0, 119, 39, 160, 120, 103, 215, 255, 119, 39, 160, 120, 103};
    const int b[] = {255, 0, 180, 40, 44, 10, 189, 215, 255, 180, 40, 44, 10, 189};
    const PLFLT a[] = {1, 1, 1, 1, 1, 1, 1, 1, 1, 0.22, 0.22, 0.22, 0.22, 0.22};
    pls_->scmap0a(r, g, b, a, 14);
    pls_->ssub(nx_sub, ny_sub);
    pls_->init();
    pls_->schr(0, 1.0);
    pls_->sfont(PL_FCI_SANS, -1, -1);
  }
  ~Figure() {
    if (pls_) {  // not finished: an exception unwinds; leave no partial file behind
      pls_.reset();
      DiscardTemporary(tmp_);
    }
  }
  plstream& operator*() { return *pls_; }
  plstream* operator->() { return pls_.get(); }
  void Finish() {
    pls_.reset();  // plend1: the device writes the file
    if (!WholePng(tmp_)) {
      DiscardTemporary(tmp_);
      const std::string hint = WriteFailureHint(path_);
      throw Error("could not write the figure " + path_.string() +
                  (hint.empty() ? "" : ": " + hint));
    }
    CommitTemporary(tmp_, path_);
  }

 private:
  /// PLplot's state (current stream, colour maps, driver table) is global: one figure at a time
  /// in the process (the Python module writes reports with the GIL released).
  static std::mutex& Mutex() {
    static std::mutex m;
    return m;
  }
  std::unique_lock<std::mutex> lock_;
  fs::path path_, tmp_;
  std::unique_ptr<plstream> pls_;
};

/// Loads a colour map into cmap1 (control points in RGB, 0..1).
void SetColourMap(plstream& pls, ColourMap map) {
  static const unsigned viridis[] = {0x440154, 0x482475, 0x414487, 0x355F8D, 0x2A788E, 0x21918C,
                                     0x22A884, 0x44BF70, 0x7AD151, 0xBDDF26, 0xFDE725};
  static const unsigned diverging[] = {0x2166AC, 0x67A9CF, 0xF7F7F7, 0xEF8A62, 0xB2182B};
  static const unsigned grey[] = {0x000000, 0xFFFFFF};
  const unsigned* c = viridis;
  size_t n = std::size(viridis);
  if (map == ColourMap::kDiverging) c = diverging, n = std::size(diverging);
  if (map == ColourMap::kGrey) c = grey, n = std::size(grey);
  std::vector<PLFLT> pos(n), r(n), g(n), b(n);
  for (size_t i = 0; i < n; ++i) {
    const unsigned v = map == ColourMap::kViridisReversed ? c[n - 1 - i] : c[i];
    pos[i] = double(i) / double(n - 1);
    r[i] = ((v >> 16) & 255) / 255.0, g[i] = ((v >> 8) & 255) / 255.0, b[i] = (v & 255) / 255.0;
  }
  pls.scmap1n(256);
  pls.scmap1l(true, PLINT(n), pos.data(), r.data(), g.data(), b.data(), nullptr);
}

/// A vertical colour bar right of the current viewport for values lo..hi, labelled `label`.
void ColourBar(plstream& pls, double lo, double hi, const std::string& label) {
  PLFLT w = 0, h = 0;
  PLINT label_opts[] = {PL_COLORBAR_LABEL_RIGHT};
  const std::string lab = Esc(label);
  const char* labels[] = {lab.c_str()};
  const char* axis_opts[] = {"bcvtm"};
  PLFLT ticks[] = {0};
  PLINT sub_ticks[] = {0};
  PLINT n_values[] = {2};
  PLFLT range[] = {lo, hi};
  const PLFLT* values[] = {range};
  pls.col0(kBlack);
  pls.colorbar(&w, &h, PL_COLORBAR_GRADIENT,
               PL_POSITION_RIGHT | PL_POSITION_OUTSIDE | PL_POSITION_VIEWPORT, 0.03, 0.0, 0.04, 1.0,
               kWhite, kBlack, 1, 0, 0, 0, 0, 1, label_opts, labels, 1, axis_opts, ticks, sub_ticks,
               n_values, values);
}

/// Draws `img` (row 0 at the top) into world rectangle [x0, x1] x [y0, y1] (y0 bottom) with
/// colours lo..hi of the current cmap1.
void DrawImage(plstream& pls, const Image& img, double x0, double x1, double y0, double y1,
               double lo, double hi) {
  // plimagefr places its nx x ny values on the corners of an (nx - 1) x (ny - 1) grid of cells
  // spanning [x0, x1] x [y0, y1] and fills each cell with its lower-left value: one value more
  // per axis (the last column and top row repeated) gives every pixel its own cell.
  const int nx = img.width, ny = img.height;
  std::vector<PLFLT> data(size_t(nx + 1) * (ny + 1));
  std::vector<const PLFLT*> cols(nx + 1);
  for (int x = 0; x <= nx; ++x) {
    for (int iy = 0; iy <= ny; ++iy)
      data[size_t(x) * (ny + 1) + iy] =
          std::clamp(double(img.at(std::min(x, nx - 1), ny - 1 - std::min(iy, ny - 1))), lo, hi);
    cols[x] = &data[size_t(x) * (ny + 1)];
  }
  pls.imagefr(cols.data(), nx + 1, ny + 1, x0, x1, y0, y1, lo, hi, lo, hi, nullptr, nullptr);
}

std::pair<double, double> Range(const Image& img) {
  double lo = 1e300, hi = -1e300;
  for (float v : img.pixels)
    if (std::isfinite(v)) lo = std::min(lo, double(v)), hi = std::max(hi, double(v));
  if (!(hi >= lo)) lo = 0, hi = 1;
  if (hi == lo) {  // one value (e.g. a 1 x 1 matrix): a small range centred on it
    const double d = std::max(std::abs(lo) * 0.05, 1e-9);
    lo -= d, hi += d;
  }
  return {lo, hi};
}

/// PLplot labels only whole decades on a logarithmic axis: below a factor of 10 between the
/// smallest and largest value an axis stays linear (the label then says so).
bool SpansADecade(const std::vector<Series>& series, bool x) {
  double lo = 1e300, hi = 0;
  for (const Series& s : series)
    for (double v : x ? s.x : s.y)
      if (v > 0) lo = std::min(lo, v), hi = std::max(hi, v);
  return hi >= 10 * lo;
}

void Panel(plstream& pls, const PlotPanel& panel) {
  PlotPanel p = panel;
  p.log_x = p.log_x && SpansADecade(p.series, true);
  p.log_y = p.log_y && SpansADecade(p.series, false);
  if (p.log_x) p.xlabel += " (log scale)";
  if (p.log_y) p.ylabel += " (log scale)";
  auto tx = [&](double v) { return p.log_x ? std::log10(v) : v; };
  auto ty = [&](double v) { return p.log_y ? std::log10(std::max(v, 1e-300)) : v; };
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  for (const Series& s : p.series) {
    for (size_t i = 0; i < s.x.size(); ++i) {
      const double e = s.yerr.empty() ? 0 : s.yerr[i];
      x0 = std::min(x0, tx(s.x[i])), x1 = std::max(x1, tx(s.x[i]));
      y0 = std::min(y0, ty(s.y[i] - e)), y1 = std::max(y1, ty(s.y[i] + e));
    }
    for (double v : s.band_lo) y0 = std::min(y0, ty(v));
    for (double v : s.band_hi) y1 = std::max(y1, ty(v));
  }
  if (!(x1 >= x0)) x0 = 0, x1 = 1;
  if (!(y1 >= y0)) y0 = 0, y1 = 1;
  if (x1 == x0) x0 -= 0.5, x1 += 0.5;
  if (y1 == y0) y0 -= 0.5, y1 += 0.5;
  const double xp = 0.03 * (x1 - x0), yp = 0.06 * (y1 - y0);
  bool any_label = false;
  for (const Series& s : p.series) any_label |= !s.label.empty();
  // Room above the data for the legend.
  const double top = any_label ? 0.08 * double(p.series.size()) * (y1 - y0) : 0;
  pls.adv(0);
  pls.vpor(0.14, 0.96, 0.14, 0.88);
  pls.wind(x0 - xp, x1 + xp, y0 - yp, y1 + yp + top);
  const std::string xo = std::string(p.log_x ? "l" : "") + "g",
                    yo = std::string(p.log_y ? "l" : "") + "g";
  pls.col0(kGrid);
  pls.width(1);
  pls.box(xo.c_str(), 0, 0, yo.c_str(), 0, 0);
  for (size_t k = 0; k < p.series.size(); ++k) {
    const Series& s = p.series[k];
    const int colour = kSeriesColour + int(k % kSeriesColours);
    std::vector<PLFLT> x(s.x.size()), y(s.y.size());
    for (size_t i = 0; i < x.size(); ++i) x[i] = tx(s.x[i]), y[i] = ty(s.y[i]);
    if (s.band_lo.size() == x.size() && s.band_hi.size() == x.size() && !x.empty()) {
      std::vector<PLFLT> bx(x), by;
      bx.insert(bx.end(), x.rbegin(), x.rend());
      for (double v : s.band_hi) by.push_back(ty(v));
      for (size_t i = x.size(); i-- > 0;) by.push_back(ty(s.band_lo[i]));
      pls.col0(kBandColour + int(k % kSeriesColours));
      pls.fill(PLINT(bx.size()), bx.data(), by.data());
    }
    pls.col0(colour);
    pls.width(2);
    if (s.points) {
      pls.ssym(0, 2.0);
      pls.poin(PLINT(x.size()), x.data(), y.data(), 17);  // filled circle
      if (s.yerr.size() == x.size()) {
        std::vector<PLFLT> lo(x.size()), hi(x.size());
        for (size_t i = 0; i < x.size(); ++i)
          lo[i] = ty(s.y[i] - s.yerr[i]), hi[i] = ty(s.y[i] + s.yerr[i]);
        pls.erry(PLINT(x.size()), x.data(), lo.data(), hi.data());
      }
      if (s.joined && x.size() > 1) pls.line(PLINT(x.size()), x.data(), y.data());
    } else if (!x.empty()) {
      pls.line(PLINT(x.size()), x.data(), y.data());
    }
  }
  pls.col0(kBlack);
  pls.width(1);
  // Up to 7 digits before PLplot switches to a common x10^n factor, so that ticks of a narrow
  // range far from zero (a deviance of 23745 +- 20) do not round to the same label.
  pls.sxax(7, 0);
  pls.syax(7, 0);
  const std::string xb = std::string("bcnst") + (p.log_x ? "l" : ""),
                    yb = std::string("bcnstv") + (p.log_y ? "l" : "");
  pls.box(xb.c_str(), 0, 0, yb.c_str(), 0, 0);
  // The y title clear of tick labels of up to 7 characters (PLplot's own sits at 5 characters).
  pls.lab(Esc(p.xlabel).c_str(), "", Esc(p.title).c_str());
  pls.mtex("l", 6.5, 0.5, 0.5, Esc(p.ylabel).c_str());
  if (!any_label) return;
  std::vector<PLINT> opt, text_colours, line_colours, line_styles, symbol_colours, symbol_numbers;
  std::vector<PLFLT> line_widths, symbol_scales;
  std::vector<std::string> texts;
  for (size_t k = 0; k < p.series.size(); ++k) {
    const Series& s = p.series[k];
    if (s.label.empty()) continue;
    const int colour = kSeriesColour + int(k % kSeriesColours);
    opt.push_back(s.points ? (s.joined ? PL_LEGEND_SYMBOL | PL_LEGEND_LINE : PL_LEGEND_SYMBOL)
                           : PL_LEGEND_LINE);
    text_colours.push_back(kBlack);
    line_colours.push_back(colour), line_styles.push_back(1), line_widths.push_back(2);
    symbol_colours.push_back(colour), symbol_scales.push_back(1), symbol_numbers.push_back(1);
    texts.push_back(Esc(s.label));
  }
  std::vector<const char*> text_ptrs, symbols;
  for (const std::string& t : texts) text_ptrs.push_back(t.c_str()), symbols.push_back("•");
  PLFLT lw = 0, lh = 0;
  pls.legend(&lw, &lh, PL_LEGEND_BACKGROUND | PL_LEGEND_BOUNDING_BOX,
             PL_POSITION_TOP | PL_POSITION_RIGHT | PL_POSITION_INSIDE, 0.01, 0.01, 0.06, kWhite,
             kBlack, 1, 0, 0, PLINT(texts.size()), opt.data(), 0.8, 0.8, 1.6, 0.0,
             text_colours.data(), text_ptrs.data(), nullptr, nullptr, nullptr, nullptr,
             line_colours.data(), line_styles.data(), line_widths.data(), symbol_colours.data(),
             symbol_scales.data(), symbol_numbers.data(), symbols.data());
}

}  // namespace

void WritePlot(const std::string& path, const std::vector<PlotPanel>& panels, int width,
               int panel_height) {
  Figure fig(path, width, panel_height * int(std::max<size_t>(1, panels.size())), 1,
             int(std::max<size_t>(1, panels.size())));
  for (const PlotPanel& p : panels) Panel(*fig, p);
  fig.Finish();
}

void WritePlot(const std::string& path, const std::vector<Series>& series, const std::string& title,
               const std::string& xlabel, const std::string& ylabel) {
  PlotPanel p;
  p.series = series;
  p.title = title, p.xlabel = xlabel, p.ylabel = ylabel;
  WritePlot(path, std::vector<PlotPanel>{p});
}

void WriteMap(const std::string& path, const MapPlot& m) {
  const int w = m.image.width, h = m.image.height;
  const double scale = double(m.max_side_px) / std::max(w, h);
  const int mw = std::max(60, int(w * scale)), mh = std::max(60, int(h * scale));
  const int left = 90, right = 170, top = 56, bottom = m.marker_legend.empty() ? 64 : 90;
  const int W = left + mw + right, H = top + mh + bottom;
  Figure fig(path, W, H);
  plstream& pls = *fig;
  auto [lo, hi] = Range(m.image);
  if (m.hi > m.lo) lo = m.lo, hi = m.hi;
  std::vector<double> xe = m.x_edges, ye = m.y_edges;
  const bool pixel_axes = m.x_left == 0 && m.x_right == 0 && m.y_top == 0 && m.y_bottom == 0;
  const double xl = pixel_axes ? 0 : m.x_left, xr = pixel_axes ? w : m.x_right;
  const double yt = pixel_axes ? 0 : m.y_top, yb = pixel_axes ? h : m.y_bottom;  // rows count down
  if (xe.size() != size_t(w) + 1) {
    xe.resize(w + 1);
    for (int i = 0; i <= w; ++i) xe[i] = xl + (xr - xl) * i / w;
  }
  if (ye.size() != size_t(h) + 1) {
    ye.resize(h + 1);
    for (int i = 0; i <= h; ++i) ye[i] = yt + (yb - yt) * i / h;
  }
  pls.adv(0);
  pls.vpor(double(left) / W, double(left + mw) / W, double(bottom) / H, double(bottom + mh) / H);
  pls.wind(xe.front(), xe.back(), ye.back(), ye.front());
  SetColourMap(pls, m.map);
  const bool uniform = m.x_edges.empty() && m.y_edges.empty();
  if (uniform) {
    DrawImage(pls, m.image, xe.front(), xe.back(), ye.back(), ye.front(), lo, hi);
  } else {
    // Non-uniform cells (e.g. defocus planes): one filled rectangle per cell in cmap1.
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const double v = m.image.at(x, y);
        pls.col1(std::clamp(hi > lo ? (v - lo) / (hi - lo) : 0.5, 0.0, 1.0));
        PLFLT px[] = {xe[x], xe[x + 1], xe[x + 1], xe[x]},
              py[] = {ye[y], ye[y], ye[y + 1], ye[y + 1]};
        pls.fill(4, px, py);
      }
  }
  for (const MapMarker& k : m.markers) {
    PLFLT px[] = {k.x}, py[] = {k.y};
    pls.col0(k.emphasis ? kMarkerWhite : kSeriesColour + 1);
    pls.schr(0, k.emphasis ? 2.2 : 1.1);
    pls.string(1, px, py, k.emphasis ? "□" : "●");
  }
  pls.schr(0, 1.0);
  pls.col0(kBlack);
  pls.box("bcnst", 0, 0, "bcnstv", 0, 0);
  pls.lab(Esc(m.xlabel).c_str(), Esc(m.ylabel).c_str(), Esc(m.title).c_str());
  if (!m.marker_legend.empty()) {
    pls.schr(0, 0.8);
    pls.mtex("b", 6.2, 0.5, 0.5, Esc(m.marker_legend).c_str());
    pls.schr(0, 1.0);
  }
  ColourBar(pls, lo, hi, m.colour_label);
  fig.Finish();
}

void WriteImageGrid(const std::string& path, const ImageGrid& g) {
  if (g.rows.empty() || g.rows[0].empty()) throw Error("WriteImageGrid: no images (" + path + ")");
  const int nr = int(g.rows.size());
  int nc = 0;
  for (const auto& row : g.rows) nc = std::max(nc, int(row.size()));
  const int iw = g.rows[0][0].width, ih = g.rows[0][0].height;
  const int tw = std::max(iw, ih) == iw ? g.tile_px : std::max(20, g.tile_px * iw / ih);
  const int th = std::max(20, tw * ih / std::max(1, iw));
  auto labelled = [&](int r) {
    if (r >= int(g.tile_labels.size())) return false;
    for (const std::string& l : g.tile_labels[r])
      if (!l.empty()) return true;
    return false;
  };
  // Rows are 8 px apart, 26 px where the lower row has labels above its tiles.
  const int gap = 8, label_gap = 26, left = 150, right = 200, top = 96, bottom = 16;
  std::vector<int> row_top(nr);
  int y = top;
  for (int r = 0; r < nr; ++r) {
    if (r > 0) y += labelled(r) ? label_gap : gap;
    row_top[r] = y;
    y += th;
  }
  const int W = std::max(640, left + nc * tw + (nc - 1) * gap + right);
  const int H = y + bottom;
  Figure fig(path, W, H);
  plstream& pls = *fig;
  SetColourMap(pls, g.map);
  pls.adv(0);
  for (int r = 0; r < nr; ++r)
    for (int c = 0; c < int(g.rows[r].size()); ++c) {
      const double x0 = left + c * (tw + gap), y1 = H - row_top[r];
      pls.vpor(x0 / W, (x0 + tw) / W, (y1 - th) / H, y1 / H);
      pls.wind(0, iw, 0, ih);
      DrawImage(pls, g.rows[r][c], 0, iw, 0, ih, g.lo, g.hi);
      pls.col0(kBlack);
      pls.box("bc", 0, 0, "bc", 0, 0);
      pls.schr(0, tw < 140 ? 0.8 : 1.0);
      if (r < int(g.tile_labels.size()) && c < int(g.tile_labels[r].size()) &&
          !g.tile_labels[r][c].empty())
        pls.mtex("t", 0.6, 0.5, 0.5, Esc(g.tile_labels[r][c]).c_str());
      if (c == 0 && r < int(g.row_labels.size()))
        pls.mtex("lv", 0.6, 0.5, 1.0, Esc(g.row_labels[r]).c_str());
      pls.schr(0, 1.0);
    }
  // Title centred on the figure (lines split at '\n'), colour bar beside the whole grid.
  pls.vpor(0.02, 0.98, double(bottom) / H, double(H - top) / H);
  pls.wind(0, 1, 0, 1);
  pls.col0(kBlack);
  std::vector<std::string> lines;
  for (size_t a = 0, b; a <= g.title.size(); a = b + 1) {
    b = g.title.find('\n', a);
    if (b == std::string::npos) b = g.title.size();
    lines.push_back(g.title.substr(a, b - a));
  }
  for (size_t k = 0; k < lines.size(); ++k)
    pls.mtex("t", 2.6 + 1.3 * double(lines.size() - 1 - k), 0.5, 0.5, Esc(lines[k]).c_str());
  pls.vpor(double(left) / W, double(left + nc * tw + (nc - 1) * gap) / W, double(bottom) / H,
           double(H - top) / H);
  ColourBar(pls, g.lo, g.hi, g.colour_label);
  fig.Finish();
}

void WriteFalseColour(const std::string& path, const Image& img, int zoom) {
  double mx = 0;
  for (float v : img.pixels) mx = std::max(mx, double(v));
  WriteFalseColour(path, img, 0.0, mx > 0 ? mx : 1.0, zoom);
}

void WriteFalseColour(const std::string& path, const Image& img, double lo, double hi, int zoom) {
  MapPlot m;
  m.image = img;
  m.lo = lo, m.hi = hi > lo ? hi : lo + 1;
  m.map = ColourMap::kViridis;
  m.xlabel = "column", m.ylabel = "row";
  m.max_side_px = std::clamp(std::max(img.width, img.height) * zoom, 160, 640);
  WriteMap(path, m);
}

MapPlot ResidualMapPlot(const Image& residual, double object_pixel_um) {
  MapPlot p;
  p.image = residual;
  const double px = object_pixel_um > 0 ? object_pixel_um : 1.0;
  const std::string unit = object_pixel_um > 0 ? "um at the object" : "px";
  p.x_left = -0.5 * residual.width * px, p.x_right = 0.5 * residual.width * px;
  p.y_top = 0.5 * residual.height * px, p.y_bottom = -0.5 * residual.height * px;
  p.lo = -4, p.hi = 4;
  p.map = ColourMap::kDiverging;
  p.xlabel = "x (" + unit + " from the image centre)";
  p.ylabel = "y (" + unit + " from the image centre)";
  p.max_side_px = 380;
  return p;
}

}  // namespace raymatch::compare
