#pragma once
// The paper's Fig. 8 view (section III.C): two images' counts summed over a horizontal band of
// rows, column by column, and their difference with the +-1 standard-deviation shot-noise band.
// For Poisson counts the sum over a band is Poisson too, so the difference of two independent
// images' sums has the standard deviation sqrt(sum_A + sum_B) (the square root of the summed
// counts); where a model image is an expectation without noise, sqrt(sum_A) alone.
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::compare {

struct BandProfile {
  int row_begin = 0, row_end = 0;  ///< rows [begin, end) summed
  std::vector<double> a, b;        ///< per column: the band's summed counts of each image
  std::vector<double> difference;  ///< b - a
  std::vector<double> sd;          ///< shot-noise standard deviation of the difference
  /// The difference over the band's columns in units of its sd: chi-square against zero and
  /// the number of columns (a difference the noise explains gives about one per column).
  double chi2 = 0;
  int columns = 0;
};

/// Sums rows [row_begin, row_end) of `a` and `b` (same size; counts >= 0) column by column.
/// `b_noisy`: whether b carries its own Poisson noise (two measurements or two simulations),
/// else it is an expectation and only a's noise enters the band. Throws Error naming what is
/// wrong (sizes, an empty or out-of-range band).
BandProfile RowBandProfile(const Image& a, const Image& b, int row_begin, int row_end,
                           bool b_noisy = true);

/// CSV (column, x_um, sum_a, sum_b, difference, sd) and a PNG plot of the difference with the
/// +-1 sd band about zero, in `stem`.csv and `stem`.png. `pixel_um` > 0: x in micrometres at
/// the object (centred), else in columns. Labels name the two images.
void WriteBandProfile(const std::string& stem, const BandProfile& p, double pixel_um,
                      const std::string& label_a, const std::string& label_b);

}  // namespace raymatch::compare
