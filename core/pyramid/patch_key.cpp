#include "core/pyramid/patch_key.hpp"

#include <charconv>

namespace vsm::core {

std::string_view toString(Quadrant q) {
  switch (q) {
    case Quadrant::NW:
      return "nw";
    case Quadrant::NE:
      return "ne";
    case Quadrant::SW:
      return "sw";
    case Quadrant::SE:
      return "se";
  }
  return "nw";
}

std::optional<Quadrant> parseQuadrant(std::string_view name) {
  for (Quadrant q : kQuadrants) {
    const std::string_view n = toString(q);
    if (name.size() == 2 && (name[0] | 0x20) == n[0] && (name[1] | 0x20) == n[1]) {
      return q;
    }
  }
  return std::nullopt;
}

std::optional<PatchKey> PatchKey::parent() const {
  if (isRoot()) {
    return std::nullopt;
  }
  return PatchKey{depth - 1, x / 2, y / 2};
}

Quadrant PatchKey::quadrant() const {
  return static_cast<Quadrant>((x & 1) | ((y & 1) << 1));
}

PatchKey PatchKey::child(Quadrant q) const {
  const auto qi = static_cast<std::uint32_t>(q);
  return {depth + 1, x * 2 + (qi & 1), y * 2 + (qi >> 1)};
}

bool PatchKey::isAncestorOrSelfOf(const PatchKey& other) const {
  if (other.depth < depth) {
    return false;
  }
  const int shift = other.depth - depth;
  return (other.x >> shift) == x && (other.y >> shift) == y;
}

std::string_view PatchKey::toChars(char (&out)[kMaxText]) const {
  char* const end = out + kMaxText;
  char* p = std::to_chars(out, end, depth).ptr;
  *p++ = '_';
  p = std::to_chars(p, end, x).ptr;
  *p++ = '_';
  p = std::to_chars(p, end, y).ptr;
  return {out, static_cast<std::size_t>(p - out)};
}

std::string PatchKey::toString() const {
  char text[kMaxText];
  return std::string(toChars(text));
}

std::optional<PatchKey> PatchKey::parse(std::string_view text) {
  PatchKey key;
  const char* p = text.data();
  const char* end = text.data() + text.size();
  auto number = [&](auto& out) {
    if (p == end || *p < '0' || *p > '9' ||
        (*p == '0' && p + 1 != end && p[1] >= '0' && p[1] <= '9')) {
      return false;  // no sign, no leading zeros: exactly one spelling per key
    }
    const auto r = std::from_chars(p, end, out);
    if (r.ec != std::errc()) {
      return false;
    }
    p = r.ptr;
    return true;
  };
  auto separator = [&] {
    if (p == end || *p != '_') {
      return false;
    }
    ++p;
    return true;
  };
  if (!number(key.depth) || !separator() || !number(key.x) || !separator() || !number(key.y) ||
      p != end) {
    return std::nullopt;
  }
  if (key.depth > kMaxDepth || (key.depth < 32 && (key.x >> key.depth) != 0) ||
      (key.depth < 32 && (key.y >> key.depth) != 0)) {
    return std::nullopt;
  }
  return key;
}

}  // namespace vsm::core
