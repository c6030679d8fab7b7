#pragma once

#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace vsm::core {

/// Shortest text that parses back to exactly `value`; always '.' as decimal point, whatever the
/// process locale (OPC files are read by other tools in other locales).
std::string formatDouble(double value);

/// Parses a whole number in invariant form ("-1.5e3", "nan", "inf"); nullopt when `text` is not
/// exactly one number (surrounding whitespace allowed).
std::optional<double> parseDouble(std::string_view text);
std::optional<long long> parseInteger(std::string_view text);

/// Parses the bracketed lists OPC XML uses: "[1, 2, 3]" or nested "[[1, 2], [3, 4]]", flattened in
/// reading order. nullopt on anything that is not numbers, commas, brackets and whitespace, or on
/// unbalanced brackets.
std::optional<std::vector<double>> parseNumberList(std::string_view text);

}  // namespace vsm::core
