// Numbers in reports: a value carries the digits its uncertainty supports, and a quantity that
// was not determined reads "not computed", never 0.
#include "raymatch/core/html.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

namespace raymatch {
namespace {

TEST(ReportNumbers, ValueToTheUncertaintysSecondDigit) {
  EXPECT_EQ(FormatValue(1.29947, 0.00190911), "1.2995");
  EXPECT_EQ(FormatUncertainty(0.00190911), "0.0019");
  EXPECT_EQ(FormatValue(25.70512, 0.105), "25.71");
  EXPECT_EQ(FormatValue(-0.70109, 0.00151), "-0.7011");
  EXPECT_EQ(FormatValue(1234.5, 31), "1234");  // no decimals above the units digit
  EXPECT_EQ(FormatValue(22.99930, 0.00127), "22.9993");
}

TEST(ReportNumbers, UndeterminedQuantitiesAreNotZero) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(FormatUncertainty(0), "not computed");
  EXPECT_EQ(FormatUncertainty(nan), "not computed");
  EXPECT_EQ(FormatUncertainty(-1), "not computed");
  EXPECT_EQ(FormatValue(1.33885, 0), "1.33885");  // no uncertainty: 6 significant digits
  EXPECT_EQ(FormatValue(1.33885123, nan, 8), "1.3388512");
  EXPECT_EQ(FormatValue(nan, 0.1), "not computed");
}

}  // namespace
}  // namespace raymatch
