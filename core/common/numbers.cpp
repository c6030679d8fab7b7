#include "core/common/numbers.hpp"

#include <charconv>
#include <cmath>

#include "core/common/text.hpp"

namespace vsm::core {

std::string formatDouble(double value) {
  if (std::isnan(value)) {
    return "NaN";
  }
  char buffer[64];
  const auto result = std::to_chars(buffer, buffer + sizeof buffer, value);
  return std::string(buffer, result.ptr);
}

std::optional<double> parseDouble(std::string_view text) {
  text = trim(text);
  if (text.empty()) {
    return std::nullopt;
  }
  if (text.front() == '+') {
    text.remove_prefix(1);
  }
  double value = 0;
  const auto result = std::from_chars(text.data(), text.data() + text.size(), value);
  if (result.ec != std::errc() || result.ptr != text.data() + text.size()) {
    return std::nullopt;
  }
  return value;
}

std::optional<long long> parseInteger(std::string_view text) {
  text = trim(text);
  long long value = 0;
  const auto result = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || result.ec != std::errc() || result.ptr != text.data() + text.size()) {
    return std::nullopt;
  }
  return value;
}

std::optional<std::vector<double>> parseNumberList(std::string_view text) {
  std::vector<double> values;
  int depth = 0;
  bool sawBracket = false;
  std::size_t i = 0;
  while (i < text.size()) {
    const char c = text[i];
    if (c == '[') {
      ++depth;
      sawBracket = true;
      ++i;
    } else if (c == ']') {
      if (--depth < 0) {
        return std::nullopt;
      }
      ++i;
    } else if (c == ',' || c == ' ' || c == '\t' || c == '\n' || c == '\r') {
      ++i;
    } else {
      std::size_t end = i;
      while (end < text.size() && text[end] != ',' && text[end] != ']' && text[end] != '[' &&
             text[end] != ' ' && text[end] != '\t' && text[end] != '\n' && text[end] != '\r') {
        ++end;
      }
      const auto value = parseDouble(text.substr(i, end - i));
      if (!value) {
        return std::nullopt;
      }
      values.push_back(*value);
      i = end;
    }
  }
  if (depth != 0 || !sawBracket) {
    return std::nullopt;
  }
  return values;
}

}  // namespace vsm::core
