#pragma once
// Parts of the fit's report (fit/src/report.cpp) that tests check directly. Not installed.
#include "raymatch/compare/plot.h"
#include "raymatch/fit/fit.h"

namespace raymatch::fit::internal {

/// A two-parameter grid fit's landscape: the error at each node as a cell centred on the node's
/// values (edges midway between nodes), the axes in the parameters' units (x the second
/// parameter, y the first), the colour bar labelled with the error function, the estimate
/// marked.
compare::MapPlot GridLandscapeMap(const FitSpec& spec, const FitResult& res);

/// The mean of an image's squared pixels (a residual map's mean square; 0 for an empty image).
double MeanSquare(const Image& image);

/// Image k's residual map, (sim - exp) / sigma on a diverging scale of +-4, its axes in um at
/// the object from the image centre (pixels where the pixel's size there is unknown).
compare::MapPlot ResidualMap(const FitResult& res, size_t k);

}  // namespace raymatch::fit::internal
