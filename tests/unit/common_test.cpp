#include <gtest/gtest.h>

#include <clocale>
#include <cmath>
#include <limits>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/common/progress.hpp"

namespace vsm::core {
namespace {

TEST(Numbers, FormatDoubleRoundTripsExactly) {
  for (const double value : {0.0, -0.0, 1.0 / 3.0, 6378137.123456789, -1e-300, 1e300, 0.1}) {
    const auto parsed = parseDouble(formatDouble(value));
    ASSERT_TRUE(parsed.has_value()) << formatDouble(value);
    EXPECT_EQ(*parsed, value);
  }
}

TEST(Numbers, ParseDoubleRejectsPartialNumbers) {
  EXPECT_FALSE(parseDouble("1.5x").has_value());
  EXPECT_FALSE(parseDouble("").has_value());
  EXPECT_FALSE(parseDouble("1,5").has_value());
  EXPECT_EQ(parseDouble(" 2.5e3 ").value(), 2500.0);
  EXPECT_EQ(parseDouble("+4").value(), 4.0);
}

TEST(Numbers, ParseNumberListFlattensNestedBrackets) {
  const auto values = parseNumberList("[[1, 0, 0, -9.4], [0, 1, 0, 39.3]]");
  ASSERT_TRUE(values.has_value());
  EXPECT_EQ(*values, (std::vector<double>{1, 0, 0, -9.4, 0, 1, 0, 39.3}));
}

TEST(Numbers, ParseNumberListRejectsGarbageAndUnbalancedBrackets) {
  EXPECT_FALSE(parseNumberList("[1, 2").has_value());
  EXPECT_FALSE(parseNumberList("1, 2]").has_value());
  EXPECT_FALSE(parseNumberList("[1, two]").has_value());
  EXPECT_FALSE(parseNumberList("1 2").has_value());
}

TEST(Numbers, ParsingIgnoresACommaDecimalLocale) {
  // OPC files are written with '.', whatever the locale of the writer or reader.
  const char* previous = std::setlocale(LC_ALL, nullptr);
  const std::string saved = previous != nullptr ? previous : "C";
  bool switched = false;
  for (const char* name : {"de_DE.UTF-8", "de_DE.utf8", "fr_FR.UTF-8", "fr_FR.utf8"}) {
    if (std::setlocale(LC_ALL, name) != nullptr && *std::localeconv()->decimal_point == ',') {
      switched = true;
      break;
    }
  }
  EXPECT_EQ(parseDouble("0.5").value(), 0.5);
  EXPECT_EQ(formatDouble(0.25), "0.25");
  EXPECT_EQ(parseNumberList("[1.5, 2.5]").value(), (std::vector<double>{1.5, 2.5}));
  std::setlocale(LC_ALL, saved.c_str());
  if (!switched) {
    GTEST_SKIP() << "no comma-decimal locale installed";
  }
}

TEST(Error, CarriesItsCode) {
  try {
    throw Error(ErrorCode::Corrupt, "bad file");
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::Corrupt);
    EXPECT_STREQ(e.what(), "bad file");
    EXPECT_EQ(toString(e.code()), "corrupt");
  }
}

TEST(CancelToken, ThrowsCancelledOnceCancelled) {
  CancelToken token;
  EXPECT_NO_THROW(token.throwIfCancelled());
  token.cancel();
  try {
    token.throwIfCancelled();
    FAIL() << "no exception";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::Cancelled);
  }
}

}  // namespace
}  // namespace vsm::core
