#pragma once

#include <string_view>

namespace vsm::core {

/// `s` without leading and trailing white space: spaces, tabs, CRs and LFs (HTTP's optional white
/// space, numbers padded in OPC XML, values in the daemon's configuration). The one trim of the
/// code base.
constexpr std::string_view trim(std::string_view s) {
  const auto isSpace = [](char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r'; };
  while (!s.empty() && isSpace(s.front())) {
    s.remove_prefix(1);
  }
  while (!s.empty() && isSpace(s.back())) {
    s.remove_suffix(1);
  }
  return s;
}

}  // namespace vsm::core
