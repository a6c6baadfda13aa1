#include "raymatch/compare/band_profile.h"

#include <cmath>
#include <sstream>

#include "raymatch/compare/plot.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"

namespace raymatch::compare {

BandProfile RowBandProfile(const Image& a, const Image& b, int row_begin, int row_end,
                           bool b_noisy) {
  if (a.width != b.width || a.height != b.height)
    throw Error("the two images differ in size: " + std::to_string(a.width) + " x " +
                std::to_string(a.height) + " and " + std::to_string(b.width) + " x " +
                std::to_string(b.height) + " pixels");
  if (!(row_begin >= 0 && row_end <= a.height && row_begin < row_end))
    throw Error("rows " + std::to_string(row_begin) + ":" + std::to_string(row_end) +
                ": expected R0:R1 with 0 <= R0 < R1 <= " + std::to_string(a.height) +
                " (the image's height; R1 is not included)");
  BandProfile p;
  p.row_begin = row_begin, p.row_end = row_end;
  p.columns = a.width;
  for (int x = 0; x < a.width; ++x) {
    double sa = 0, sb = 0;
    for (int y = row_begin; y < row_end; ++y) {
      const double va = a.at(x, y), vb = b.at(x, y);
      if (!(va >= 0 && vb >= 0))
        throw Error("column " + std::to_string(x) + ", row " + std::to_string(y) +
                    ": counts must be finite and >= 0 (photon counts, dark-subtracted)");
      sa += va, sb += vb;
    }
    const double sd = std::sqrt(sa + (b_noisy ? sb : 0.0));
    p.a.push_back(sa), p.b.push_back(sb), p.difference.push_back(sb - sa), p.sd.push_back(sd);
    if (sd > 0) p.chi2 += (sb - sa) * (sb - sa) / (sd * sd);
  }
  return p;
}

void WriteBandProfile(const std::string& stem, const BandProfile& p, double pixel_um,
                      const std::string& label_a, const std::string& label_b) {
  std::ostringstream csv;
  csv << "# rows " << p.row_begin << " to " << p.row_end - 1 << " summed; difference = B - A; sd: "
      << "shot noise of the difference\n# A: " << label_a << "\n# B: " << label_b
      << "\ncolumn,x_um,sum_a,sum_b,difference,sd\n";
  Series diff, zero;
  for (size_t x = 0; x < p.difference.size(); ++x) {
    const double xu =
        pixel_um > 0 ? (double(x) + 0.5 - 0.5 * double(p.columns)) * pixel_um : double(x);
    csv << x << "," << (pixel_um > 0 ? std::to_string(xu) : std::string()) << "," << p.a[x] << ","
        << p.b[x] << "," << p.difference[x] << "," << p.sd[x] << "\n";
    diff.x.push_back(xu), diff.y.push_back(p.difference[x]);
    zero.x.push_back(xu), zero.y.push_back(0);
    zero.band_lo.push_back(-p.sd[x]), zero.band_hi.push_back(p.sd[x]);
  }
  diff.label = "B - A (A: " + label_a + ", B: " + label_b + ")";
  zero.label = "+-1 standard deviation (shot noise)";
  WriteTextFileAtomic(stem + ".csv", csv.str());
  std::ostringstream title;
  title.precision(4);
  title << "rows " << p.row_begin << "-" << p.row_end - 1 << ": B - A and shot noise, chi-square "
        << p.chi2 << " / " << p.columns << " columns";
  WritePlot(stem + ".png", {zero, diff}, title.str(),
            pixel_um > 0 ? "x at the object (µm)" : "column (pixels)",
            "difference of the band's counts (photons)");
}

}  // namespace raymatch::compare
